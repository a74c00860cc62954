//! The evaluation (`b2dr run`): the closed loop of `sim` with the sensors at every planner step: the
//! generative renderer (`render`), the synthetic world's exact renderer (`world`) or log replay, behind the
//! simulator's [`crate::sim::sensors::Sensors`] trait. This layer sits above sim, world and render; the
//! simulator itself never touches the GPU.
pub mod batch;
pub mod chart;
pub mod compare;
pub mod fidelity;
pub mod planner_data;
pub mod prev_base;
pub mod run;
pub mod sensors;
pub mod trade;
