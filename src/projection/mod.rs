//! Geometric conditions of the renderer, on the CPU (Bench2Drive-R, renderer spec 3a, 3c, 3d, 3f). Never
//! imports `ash`.
//!
//! - [`geometry`]: classes, 3D boxes, map elements ([`MapLayer`], our own map input type: polylines and polygons in
//!   global coordinates with a class), the per-camera projector with range/frustum culling and near-plane
//!   clipping in 3D.
//! - [`raster`]: scanline polygon fill with pixel-centre sampling (even-odd), thick lines, convex hull.
//! - [`layout`]: per-class binary masks of one camera at render resolution (`(C, H, W)`, C = 10 box + 5 map
//!   classes) and box wireframes for overlays.
//! - [`retrieval`]: nearest recorded image ahead / behind along the ego heading, and hierarchical sampling of
//!   training references; [`frame_index`]: the same nearest-ahead / nearest-behind queries on a 2-d tree.
//! - [`pe`]: PETR frustum position encodings `(D*3, h, w)` in the current ego frame.
//! - [`scene`]: a scenario's boxes at a log step (gravity centres) and its map as a [`MapLayer`].
//! - [`keyframe`]: reader of the shared keyframe JSON (used by `b2dr project` and the tests).
//!
//! Conventions: ego x forward, y left, z up; camera x right, y down, z forward; image coordinates put the centre
//! of pixel index `i` at `u = i`; resizing maps `u' = (u + 0.5) s - 0.5` (PyTorch `align_corners=False`).
//! Each camera image is projected with its own ego pose at exposure time. See `docs/projection.md`.
pub mod frame_index;
pub mod geometry;
pub mod keyframe;
pub mod layout;
pub mod pe;
pub mod raster;
pub mod retrieval;
pub mod scene;

pub use frame_index::FrameIndex;
pub use geometry::{
    channel_name, Box3d, BoxClass, CameraProjector, MapClass, MapElement, MapGeometry, MapLayer,
    ProjectionConfig, NUM_MASK_CHANNELS,
};
pub use keyframe::KeyFrame;
pub use layout::{box_wireframe, LayoutMasks, LayoutRenderer};
pub use pe::{position_encoding, PeConfig, PixelGrid};
pub use raster::Rasterizer;
pub use retrieval::{retrieve, sample_training_references, Reference, References};

/// Render resolution of the generative renderer (width, height).
pub const RENDER_SIZE: (u32, u32) = (400, 224);
