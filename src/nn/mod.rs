//! Model components of the SD1.5 family (UNet2DConditionModel, ControlNetModel, AutoencoderKL): their
//! diffusers configs ([`config`]) and host-side weights ([`weights`]). The device-side modules build on
//! these.

pub mod config;
pub mod weights;
