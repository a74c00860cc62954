//! Frame rendering (Bench2Drive-R): the library API above `nn` and `projection` that turns one simulated
//! moment into camera images with the generative renderer.
//! - [`frame`]: one frame planned once per shape on the device (previous-frame chain, reference encoding,
//!   batched sampling with reference guidance, decode, upsample), replayed every frame.
//! - [`inputs`]: host-side inputs from a scene state (masks, PETR geometry, images, seeded noise).
//! - [`job`]: `b2dr render` of a keyframe.
//! - [`named`]: one frame on explicit named input tensors (`b2dr forward --component frame`; parity checks).
//! - [`package`]: the model package folder (`docs/b2dr_controlnet.md` section 5) and the built-in model.
pub mod bench;
pub mod frame;
pub mod inputs;
pub mod job;
pub mod named;
pub mod package;
pub mod warp;
