//! Reference retrieval from the recorded log (Bench2Drive-R, renderer spec 3c and 3f).
//!
//! Position of a recorded image: the translation of its own `ego2global` (the ego at that camera's exposure).
//! Heading of the current ego `v_ego`: its x axis projected on the ground plane and normalised (a yaw).
//! `P_i = (coord_i - coord_ego) . v_ego` with the ground-plane (x, y) coordinates; the front reference is the
//! image with the smallest `P_i > 0`, the rear one the image with the largest `P_i < 0`. Frames without an image
//! of the requested camera are skipped. Ties go to the earliest frame.
use glam::{DMat4, DVec2};
use rand::Rng;

use crate::scene::camera::RecordedFrame;

/// A candidate image: (frame, image, P_i).
type Cand = (usize, usize, f64);

/// One retrieved reference image.
#[derive(Clone, Debug, PartialEq)]
pub struct Reference {
    /// Index into the log's frames.
    pub frame: usize,
    /// Index of the camera's image within that frame's images.
    pub image: usize,
    /// Signed distance along the current heading `P_i` (metres; > 0 ahead, < 0 behind).
    pub along: f64,
    /// Reference ego (at the image's exposure) -> current ego: `inv(cur_ego2global) * ref_ego2global`.
    pub ref2cur: DMat4,
}

impl Reference {
    /// Camera -> current ego for this reference image (the `cam2cur` of its position encodings).
    pub fn cam2cur(&self, camera: &crate::scene::camera::Camera) -> DMat4 {
        self.ref2cur * camera.cam2ego
    }
}

/// The two references of one camera; `None` on a side where the log has no image.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct References {
    pub front: Option<Reference>,
    pub rear: Option<Reference>,
}

/// Unit heading of a pose on the ground plane (its x axis, z dropped); `None` for a vertical x axis.
pub fn heading_2d(ego2global: &DMat4) -> Option<DVec2> {
    let h = ego2global.x_axis.truncate().truncate();
    (h.length() > 1e-9).then(|| h.normalize())
}

/// `(frame, image, P_i)` for every frame holding an image of `camera`.
fn along_distances<'a>(
    frames: &'a [RecordedFrame],
    camera: &'a str,
    ego2global: &DMat4,
) -> impl Iterator<Item = (usize, usize, f64)> + 'a {
    let origin = ego2global.w_axis.truncate().truncate();
    let v = heading_2d(ego2global);
    frames.iter().enumerate().filter_map(move |(f, fr)| {
        let v = v?;
        let (i, img) = fr
            .images
            .iter()
            .enumerate()
            .find(|(_, im)| im.camera == camera)?;
        let c = img.ego2global.w_axis.truncate().truncate();
        Some((f, i, (c - origin).dot(v)))
    })
}

fn make_ref(
    frames: &[RecordedFrame],
    cur_inv: &DMat4,
    (f, i, along): (usize, usize, f64),
) -> Reference {
    Reference {
        frame: f,
        image: i,
        along,
        ref2cur: *cur_inv * frames[f].images[i].ego2global,
    }
}

/// Nearest recorded image of `camera` ahead of and behind the ego pose `ego2global` (see the module docs).
pub fn retrieve(frames: &[RecordedFrame], camera: &str, ego2global: &DMat4) -> References {
    let mut front: Option<(usize, usize, f64)> = None;
    let mut rear: Option<(usize, usize, f64)> = None;
    for c in along_distances(frames, camera, ego2global) {
        if c.2 > 0.0 && front.is_none_or(|b| c.2 < b.2) {
            front = Some(c);
        } else if c.2 < 0.0 && rear.is_none_or(|b| c.2 > b.2) {
            rear = Some(c);
        }
    }
    let inv = ego2global.inverse();
    References {
        front: front.map(|c| make_ref(frames, &inv, c)),
        rear: rear.map(|c| make_ref(frames, &inv, c)),
    }
}

/// Distance intervals (metres, `[lo, hi)`) and their probabilities for training-time reference sampling.
pub const TRAINING_INTERVALS: [(f64, f64, f64); 3] =
    [(2.0, 5.0, 0.1), (5.0, 10.0, 0.3), (10.0, 15.0, 0.6)];

/// Hierarchical sampling of training references for frame `train` of the log (spec 3f). For each side
/// independently: an interval is drawn with probabilities 0.1 / 0.3 / 0.6 among the intervals that hold at least
/// one image on that side (renormalised; `|P_i|` in `[lo, hi)`), then an image uniformly within it. A side with
/// no image in any interval is `None`. The training frame's own pose is the pose of its `camera` image.
pub fn sample_training_references<R: Rng>(
    frames: &[RecordedFrame],
    camera: &str,
    train: usize,
    rng: &mut R,
) -> References {
    let Some(pose) = frames
        .get(train)
        .and_then(|f| f.image(camera))
        .map(|i| i.ego2global)
    else {
        return References::default();
    };
    let cands: Vec<(usize, usize, f64)> = along_distances(frames, camera, &pose)
        .filter(|c| c.0 != train)
        .collect();
    let inv = pose.inverse();
    let mut pick = |ahead: bool| -> Option<Reference> {
        let side: Vec<&Cand> = cands
            .iter()
            .filter(|c| (c.2 > 0.0) == ahead && c.2 != 0.0)
            .collect();
        let buckets: Vec<(f64, Vec<&Cand>)> = TRAINING_INTERVALS
            .iter()
            .map(|&(lo, hi, p)| {
                (
                    p,
                    side.iter()
                        .copied()
                        .filter(|c| c.2.abs() >= lo && c.2.abs() < hi)
                        .collect(),
                )
            })
            .filter(|(_, v): &(f64, Vec<_>)| !v.is_empty())
            .collect();
        let total: f64 = buckets.iter().map(|b| b.0).sum();
        if buckets.is_empty() {
            return None;
        }
        let mut r = rng.gen::<f64>() * total;
        let mut chosen = &buckets[buckets.len() - 1].1;
        for (p, v) in &buckets {
            if r < *p {
                chosen = v;
                break;
            }
            r -= p;
        }
        let c = *chosen[rng.gen_range(0..chosen.len())];
        Some(make_ref(frames, &inv, c))
    };
    let front = pick(true);
    let rear = pick(false);
    References { front, rear }
}
