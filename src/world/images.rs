//! The image store of one scenario: the pixels of its recorded images at a requested size.
//!
//! Generated images (`builtin://<scenario>/<CAMERA>/<step>`, [`ImageRef::Generated`]) are rendered by the
//! ground-truth renderer from the scenario at that log step, with the image's own recorded ego pose, and kept in
//! an in-memory cache (FIFO, [`ImageStore::with_capacity`] images); nothing is written to disk. File images are
//! read relative to the scenario's directory, undistorted when their camera has a lens distortion
//! ([`crate::scene::camera::Camera::undistort_image`]), and resized (bilinear) to the requested size.
use super::render::{render_cameras, RenderOptions};
use super::{objects_at, World};
use crate::scene::camera::{CameraImage, ImageRef};
use crate::scene::Scenario;
use anyhow::{bail, ensure, Context, Result};
use std::collections::{HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

/// An RGB image `(H, W, 3)` interleaved, u8.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbPixels {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

type Key = (String, usize, usize);
/// The cached images and their insertion order (FIFO eviction).
type Cache = (HashMap<Key, Arc<RgbPixels>>, VecDeque<Key>);

/// Resolves and caches the recorded images of one scenario.
pub struct ImageStore<'a> {
    world: World<'a>,
    base_dir: Option<PathBuf>,
    capacity: usize,
    cache: Mutex<Cache>,
    index: OnceLock<crate::projection::FrameIndex>,
}

impl<'a> ImageStore<'a> {
    /// A store for `sc`; file images are looked up under `base_dir` (the scenario file's directory).
    pub fn new(sc: &'a Scenario, base_dir: Option<PathBuf>) -> Self {
        Self::with_capacity(sc, base_dir, 512)
    }

    pub fn with_capacity(sc: &'a Scenario, base_dir: Option<PathBuf>, capacity: usize) -> Self {
        ImageStore {
            world: World::new(sc),
            base_dir,
            capacity: capacity.max(1),
            cache: Mutex::new((HashMap::new(), VecDeque::new())),
            index: OnceLock::new(),
        }
    }

    /// The retrieval index over the scenario's recorded frames (built on first use).
    pub fn frame_index(&self) -> &crate::projection::FrameIndex {
        self.index
            .get_or_init(|| crate::projection::FrameIndex::new(&self.world.scenario.rig.frames))
    }

    pub fn world(&self) -> &World<'a> {
        &self.world
    }

    /// The pixels of `img` at `width x height`.
    pub fn image(&self, img: &CameraImage, width: usize, height: usize) -> Result<Arc<RgbPixels>> {
        let key = (img.path.clone(), width, height);
        if let Some(hit) = self.cache.lock().ok().and_then(|c| c.0.get(&key).cloned()) {
            return Ok(hit);
        }
        let px = Arc::new(self.load(img, width, height)?);
        if let Ok(mut c) = self.cache.lock() {
            if c.0.len() >= self.capacity {
                if let Some(old) = c.1.pop_front() {
                    c.0.remove(&old);
                }
            }
            if c.0.insert(key.clone(), px.clone()).is_none() {
                c.1.push_back(key);
            }
        }
        Ok(px)
    }

    fn load(&self, img: &CameraImage, width: usize, height: usize) -> Result<RgbPixels> {
        let sc = self.world.scenario;
        match img.source()? {
            ImageRef::Generated {
                scenario,
                camera,
                step,
            } => {
                ensure!(
                    scenario == sc.name,
                    "image {:?} belongs to scenario {scenario:?}, not {:?}",
                    img.path,
                    sc.name
                );
                ensure!(
                    step < sc.len(),
                    "image {:?}: step {step} is beyond the log ({} steps)",
                    img.path,
                    sc.len()
                );
                let Some(cam) = sc.rig.camera(camera) else {
                    bail!("image {:?}: the rig has no camera {camera:?}", img.path);
                };
                let objects = objects_at(sc, step);
                let f = render_cameras(
                    &self.world.scenery,
                    std::slice::from_ref(cam),
                    &img.ego2global,
                    width,
                    height,
                    &objects,
                    &RenderOptions::default(),
                    1,
                )?
                .remove(0);
                Ok(RgbPixels {
                    width,
                    height,
                    data: f.rgb,
                })
            }
            ImageRef::File(p) => {
                let path = match &self.base_dir {
                    Some(d) => d.join(p),
                    None => PathBuf::from(p),
                };
                let Some(table) = sc.rig.camera(&img.camera) else {
                    bail!(
                        "recorded image {}: the rig has no camera {:?} to give its size",
                        path.display(),
                        img.camera
                    );
                };
                let mut im = read_recorded_image(&path, (table.width, table.height), &table.name)?;
                if let Some(cam) = sc.rig.camera(&img.camera).filter(|c| c.is_distorted()) {
                    // a distorted lens: undistort at the file's size (the calibration's), then resize
                    let (w0, h0) = im.dimensions();
                    let data =
                        cam.rescaled(w0, h0)
                            .undistort_image(im.as_raw(), w0 as usize, h0 as usize);
                    im = image::RgbImage::from_raw(w0, h0, data)
                        .context("internal: undistorted image size")?;
                }
                let im = image::imageops::resize(
                    &im,
                    width as u32,
                    height as u32,
                    image::imageops::FilterType::Triangle,
                );
                Ok(RgbPixels {
                    width,
                    height,
                    data: im.into_raw(),
                })
            }
        }
    }
}

/// Reads a recorded camera image that its table (the log's camera calibration, a keyframe's `cameras`) says is
/// `table` = (width, height) pixels (issue #36, items 3 and 5): the path must be a regular file of at most
/// [`crate::files::IMAGE_LIMIT`] bytes; the image's own header is read first and must announce exactly the
/// table's size (a 1x1 JPEG where the table says 1600x900 is an error naming both, not a blurred planner input
/// or training target), and only then is it decoded, so decoding never allocates more than the table's size.
pub fn read_recorded_image(
    path: &std::path::Path,
    table: (u32, u32),
    camera: &str,
) -> Result<image::RgbImage> {
    let bytes = crate::files::read_regular(path, "recorded image", crate::files::IMAGE_LIMIT)?;
    let reader = || {
        image::ImageReader::new(std::io::Cursor::new(&bytes[..]))
            .with_guessed_format()
            .with_context(|| format!("recorded image {}: unknown format", path.display()))
    };
    let dims = reader()?
        .into_dimensions()
        .with_context(|| format!("recorded image {}: unreadable header", path.display()))?;
    ensure!(
        dims == table,
        "recorded image {} is {}x{} pixels, but its table says camera {camera} records {}x{}",
        path.display(),
        dims.0,
        dims.1,
        table.0,
        table.1
    );
    let mut r = reader()?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(table.0);
    limits.max_image_height = Some(table.1);
    r.limits(limits);
    let im = r
        .decode()
        .with_context(|| format!("decoding recorded image {}", path.display()))?
        .to_rgb8();
    ensure!(
        im.dimensions() == table,
        "recorded image {}: decoded {:?}, its header said {:?}",
        path.display(),
        im.dimensions(),
        table
    );
    Ok(im)
}
