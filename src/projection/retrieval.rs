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

/// Draws an interval index with the probabilities of [`TRAINING_INTERVALS`] restricted to `allowed`
/// (renormalised); `None` when nothing is allowed.
fn draw_interval<R: Rng>(allowed: [bool; 3], rng: &mut R) -> Option<usize> {
    let total: f64 = (0..3)
        .filter(|&i| allowed[i])
        .map(|i| TRAINING_INTERVALS[i].2)
        .sum();
    if total <= 0.0 {
        return None;
    }
    let mut r = rng.gen::<f64>() * total;
    let mut last = None;
    for (i, iv) in TRAINING_INTERVALS.iter().enumerate() {
        if !allowed[i] {
            continue;
        }
        last = Some(i);
        if r < iv.2 {
            return Some(i);
        }
        r -= iv.2;
    }
    last
}

/// Training references as a pair, one slot ahead and one behind where the log allows (the export's rule; spec
/// 3g). Per slot: an interval is drawn with probabilities 0.1 / 0.3 / 0.6 over ALL intervals; the slot takes an
/// image of its own side in that interval, or, when its side has none there, an image of the other side in the
/// same interval (both references then lie on one side); only when the interval is empty on both sides is it
/// redrawn among the intervals that hold an image on either side (renormalised). So the distance frequencies
/// are the spec's wherever the log holds images in every interval. `None` when no image lies in 2-15 m.
/// `[ahead slot, behind slot]`; the chosen image is uniform within its interval and side.
pub fn sample_reference_pair<R: Rng>(
    frames: &[RecordedFrame],
    camera: &str,
    train: usize,
    rng: &mut R,
) -> Option<[Reference; 2]> {
    let pose = frames.get(train)?.image(camera)?.ego2global;
    let cands: Vec<Cand> = along_distances(frames, camera, &pose)
        .filter(|c| c.0 != train && c.2 != 0.0)
        .collect();
    let bucket = |ahead: bool, i: usize| -> Vec<Cand> {
        let (lo, hi, _) = TRAINING_INTERVALS[i];
        cands
            .iter()
            .copied()
            .filter(|c| (c.2 > 0.0) == ahead && c.2.abs() >= lo && c.2.abs() < hi)
            .collect()
    };
    let buckets: [[Vec<Cand>; 3]; 2] = [
        [bucket(true, 0), bucket(true, 1), bucket(true, 2)],
        [bucket(false, 0), bucket(false, 1), bucket(false, 2)],
    ];
    let nonempty: [bool; 3] =
        std::array::from_fn(|i| !buckets[0][i].is_empty() || !buckets[1][i].is_empty());
    let inv = pose.inverse();
    let mut pick = |side: usize| -> Option<Reference> {
        let mut i = draw_interval([true; 3], rng)?;
        if !nonempty[i] {
            i = draw_interval(nonempty, rng)?;
        }
        let own = &buckets[side][i];
        let v = if own.is_empty() {
            &buckets[1 - side][i]
        } else {
            own
        };
        let c = v[rng.gen_range(0..v.len())];
        Some(make_ref(frames, &inv, c))
    };
    let a = pick(0)?;
    let b = pick(1)?;
    Some([a, b])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::camera::CameraImage;
    use rand::SeedableRng;

    fn line_frames(n: usize, spacing: f64) -> Vec<RecordedFrame> {
        (0..n)
            .map(|k| {
                let m = DMat4::from_translation(glam::DVec3::new(k as f64 * spacing, 0.0, 0.0));
                RecordedFrame {
                    timestamp_us: k as i64,
                    ego2global: m,
                    images: vec![CameraImage {
                        camera: "C".into(),
                        path: String::new(),
                        timestamp_us: k as i64,
                        ego2global: m,
                    }],
                }
            })
            .collect()
    }

    #[test]
    fn pair_follows_interval_probabilities() {
        let frames = line_frames(100, 0.7);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let mut counts = [0usize; 3];
        let mut n = 0;
        for t in 0..4000 {
            let train = 25 + t % 50;
            let [a, b] = sample_reference_pair(&frames, "C", train, &mut rng).unwrap();
            assert!(a.along > 0.0 && b.along < 0.0);
            for r in [a, b] {
                let d = r.along.abs();
                let i = TRAINING_INTERVALS
                    .iter()
                    .position(|iv| d >= iv.0 && d < iv.1)
                    .unwrap();
                counts[i] += 1;
                n += 1;
            }
        }
        for (i, c) in counts.iter().enumerate() {
            let f = *c as f64 / n as f64;
            assert!((f - TRAINING_INTERVALS[i].2).abs() < 0.02, "{counts:?}");
        }
        // At the log start nothing lies behind: both slots ahead.
        let [a, b] = sample_reference_pair(&frames, "C", 0, &mut rng).unwrap();
        assert!(a.along > 0.0 && b.along > 0.0);
        // A standstill log: nothing in 2-15 m.
        assert!(sample_reference_pair(&line_frames(10, 0.01), "C", 5, &mut rng).is_none());
    }
}
