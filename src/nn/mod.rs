//! Model components of the SD1.5 family (UNet2DConditionModel, ControlNetModel, AutoencoderKL): their
//! diffusers configs ([`config`]), host-side weights ([`weights`]), and the device modules (named after the
//! diffusers modules) that record their forward passes with the ops.
pub mod b2dr;
pub mod b2dr_config;
pub mod bench;
pub mod config;
pub mod controlnet;
pub mod device;
pub mod layers;
pub mod pipeline;
pub mod resnet;
pub mod run;
pub mod sd_model;
pub mod transformer;
pub mod unet;
pub mod vae;
pub mod weights;
