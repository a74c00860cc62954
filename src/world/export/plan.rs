//! Which training samples a scenario yields, decided without rendering anything (so tests can check the
//! reference statistics over thousands of samples quickly).
//!
//! Candidate frames: for generated logs (`builtin:`) every log step is a recorded frame (any step can be
//! rendered, [`crate::scene::camera::ImageRef::Generated`]); for imported logs the rig's recorded frames. A
//! target is a candidate frame with a previous frame 0.5 s (+-0.1 s) earlier; references come from
//! [`sample_reference_pair`] per camera (slot 0 ahead, slot 1 behind where the log allows). Targets without any
//! reference within 2-15 m (standstill) are skipped. Every sample is exported once per requested ego offset;
//! its references and previous frame are always the log's.
use crate::projection::retrieval::{sample_reference_pair, Reference};
use crate::scene::camera::{Camera, RecordedFrame};
use crate::scene::geometry::Pose2;
use crate::scene::import::frames_from_ego;
use crate::scene::Scenario;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Gap between a target and its previous frame (s).
pub const PREV_GAP_S: f64 = 0.5;

/// The frames training samples are drawn from (see the module docs).
pub fn candidate_frames(sc: &Scenario) -> Vec<RecordedFrame> {
    if sc.source.starts_with("builtin:") {
        frames_from_ego(&sc.name, &sc.ego, sc.dt, 1)
    } else {
        sc.rig.frames.clone()
    }
}

/// One planned sample.
#[derive(Clone, Debug, PartialEq)]
pub struct SamplePlan {
    /// Index into the candidate frames of the target and of its previous frame.
    pub frame: usize,
    pub prev: usize,
    /// With `prev_chain`: the previous frame's own previous frame (0.5 s before `prev`).
    pub prev2: Option<usize>,
    /// Log step of the target (its objects).
    pub step: usize,
    pub offset: Pose2,
    /// Per camera (order of the exported cameras): `[ahead slot, behind slot]`.
    pub refs: Vec<[Reference; 2]>,
}

/// Log step of a frame (nearest step to its timestamp).
pub fn frame_step(sc: &Scenario, f: &RecordedFrame) -> usize {
    ((f.timestamp_us as f64 * 1e-6 / sc.dt).round().max(0.0) as usize)
        .min(sc.len().saturating_sub(1))
}

/// The previous frame of frame `i`: the latest frame 0.4-0.6 s earlier.
fn prev_of(frames: &[RecordedFrame], i: usize) -> Option<usize> {
    let t = frames[i].timestamp_us;
    (0..i).rev().find(|&j| {
        let dt = (t - frames[j].timestamp_us) as f64 * 1e-6;
        (PREV_GAP_S - 0.1..=PREV_GAP_S + 0.1).contains(&dt)
    })
}

/// Plans up to `n` samples of `sc` (fewer when the log has fewer usable targets), each once per offset of
/// `offsets`. Deterministic in `seed`. `prev_chain`: only targets whose previous frame has a previous frame
/// too (`SamplePlan::prev2`; a two-frame chain for training on the model's own rollout).
pub fn plan_samples(
    sc: &Scenario,
    frames: &[RecordedFrame],
    cams: &[Camera],
    n: usize,
    offsets: &[Pose2],
    seed: u64,
    prev_chain: bool,
) -> Vec<SamplePlan> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut targets: Vec<(usize, usize, Option<usize>)> = (0..frames.len())
        .filter_map(|i| {
            let has_all = cams.iter().all(|c| frames[i].image(&c.name).is_some());
            let p = prev_of(frames, i).filter(|_| has_all)?;
            if !prev_chain {
                return Some((i, p, None));
            }
            prev_of(frames, p).map(|p2| (i, p, Some(p2)))
        })
        .collect();
    targets.shuffle(&mut rng);
    let mut out = Vec::new();
    let mut taken = 0;
    for (i, p, p2) in targets {
        if taken == n {
            break;
        }
        let refs: Option<Vec<[Reference; 2]>> = cams
            .iter()
            .map(|c| sample_reference_pair(frames, &c.name, i, &mut rng))
            .collect();
        let Some(refs) = refs else { continue };
        taken += 1;
        for o in offsets {
            out.push(SamplePlan {
                frame: i,
                prev: p,
                prev2: p2,
                step: frame_step(sc, &frames[i]),
                offset: *o,
                refs: refs.clone(),
            });
        }
    }
    out.sort_by_key(|s| s.frame); // stable: offsets stay in the order given
    out
}
