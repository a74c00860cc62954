//! The previous-frame input of a model that starts from its retrieved references (b2dr.json `prev_source`
//! "reference" or "composite"): per camera the reference behind it warped to the current pose, with, for
//! "composite", the agents' pixels taken from the frame rendered before. Host side; nothing touches the device.
use anyhow::{ensure, Result};
use glam::DMat4;

use crate::eval::sensors::Retrieved;
use crate::nn::b2dr_config::PrevSource;
use crate::ops::reference::image::warp_bilinear;
use crate::ops::warp::NO_SOURCE;
use crate::projection::scene::boxes_at;
use crate::projection::{BoxClass, MapLayer, ProjectionConfig};
use crate::render::inputs;
use crate::render::warp::{ground_warp_grid, reference_base_choice};
use crate::scene::camera::Camera;
use crate::scene::Scenario;
use crate::world::export::plan::frame_step;

/// The least fraction of a camera's pixels the warp of its chosen reference must reach (a source inside the
/// reference image) for a model with `prev_source` "reference" to start from it. Retrieval is by position
/// along the heading only: where the log turned, or on the side cameras, the reference can look elsewhere and
/// most of the frame would keep the reference's own unwarped pixels; such a camera takes the fallback instead
/// (the frame rendered before, as `prev_source` "previous" does). Measured on the training export's references
/// (2-15 m away): 95 % of CAM_FRONT's chosen references reach at least 94 % of the pixels, 3.5 % under 60 %; the
/// side cameras' medians are 59-79 %, so they mostly fall back.
pub const MIN_REFERENCE_COVERAGE: f64 = 0.9;

/// Pixels of margin around the agents of a composite base (the layout's box edges and the warp's bilinear
/// spread both blur an agent's outline by about a pixel).
pub const AGENT_MARGIN_PX: usize = 1;

/// Where a "composite" base takes the frame rendered before instead of the reference: the agents of the
/// current layout and of each reference's own log step.
pub struct AgentPixels<'a> {
    /// The current layout masks `(N, 15, H, W)` (box channels first).
    pub masks: &'a [f32],
    /// Per camera, per retrieved reference (front, rear), its logged agents in its own image `(H, W)`.
    pub refs: &'a [[Vec<bool>; 2]],
}

/// Per camera and reference, the pixels of the reference image that hold one of the log's agents at that
/// image's log step (the layout's box channels, projected from the reference's own pose).
pub fn reference_agents(
    sc: &Scenario,
    cameras: &[Camera],
    r: &Retrieved,
    size: (usize, usize),
) -> Result<Vec<[Vec<bool>; 2]>> {
    ensure!(
        r.frames.len() == cameras.len() && r.poses.len() == cameras.len(),
        "reference agents: {} cameras, references of {}",
        cameras.len(),
        r.frames.len()
    );
    let empty = MapLayer::new(vec![]);
    let hw = size.0 * size.1;
    let nb = BoxClass::ALL.len();
    let mut out = Vec::with_capacity(cameras.len());
    for (i, c) in cameras.iter().enumerate() {
        let mut pair: [Vec<bool>; 2] = [vec![], vec![]];
        for (j, m) in pair.iter_mut().enumerate() {
            let f = r.frames[i][j];
            ensure!(
                f < sc.rig.frames.len(),
                "reference agents: frame {f} of a log of {}",
                sc.rig.frames.len()
            );
            let bx: Vec<_> = boxes_at(sc, frame_step(sc, &sc.rig.frames[f]))
                .into_iter()
                .map(|(_, b)| b)
                .collect();
            let mk = inputs::masks(
                std::slice::from_ref(c),
                &[r.poses[i][j]],
                &bx,
                &empty,
                size,
                &ProjectionConfig::default(),
            )?;
            *m = (0..hw)
                .map(|p| (0..nb).any(|ch| mk[ch * hw + p] > 0.5))
                .collect();
        }
        out.push(pair);
    }
    Ok(out)
}

/// `img` `(C, H, W)` bilinearly warped by `grid` `(H, W, 2)` (the device's `warp_bilinear`: a pixel without a
/// source keeps its own value).
fn warp(img: &[f32], grid: &[f32], c: usize, size: (usize, usize)) -> Vec<f32> {
    let x: Vec<f64> = img.iter().map(|&v| v as f64).collect();
    let g: Vec<f64> = grid.iter().map(|&v| v as f64).collect();
    warp_bilinear(&x, &g, 1, c, size.0, size.1)
        .into_iter()
        .map(|v| v as f32)
        .collect()
}

/// `m` `(H, W)` grown by `r` pixels (a square neighbourhood).
fn dilate(m: &[bool], size: (usize, usize), r: usize) -> Vec<bool> {
    let (h, w) = size;
    let mut out = vec![false; h * w];
    for y in 0..h {
        for x in 0..w {
            if m[y * w + x] {
                for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                        out[yy * w + xx] = true;
                    }
                }
            }
        }
    }
    out
}

/// The previous-frame input of a model that takes it from its references (b2dr.json `prev_source`
/// "reference" / "composite"), per camera: the reference [`reference_base_choice`] picks of the two retrieved
/// (`r`), warped from its pose to `e2g`, where that warp reaches at least [`MIN_REFERENCE_COVERAGE`] of the
/// pixels, else the camera's slice of `fallback` (planar `(N, 3, H, W)` in [0, 1], the frame rendered before)
/// warped from `fallback_poses`. With `agents` ("composite"), a camera that takes its reference gets it already
/// warped, with the pixels of the current layout's agents and of the reference's own logged agents (plus
/// [`AGENT_MARGIN_PX`]) replaced by the warped fallback, and a grid that keeps every pixel. Returns the images,
/// the warp grids `(N, H, W, 2)` and per camera whether it took the reference.
#[allow(clippy::too_many_arguments)]
pub fn reference_base(
    cameras: &[Camera],
    e2g: &DMat4,
    r: &Retrieved,
    size: (usize, usize),
    max_depth: f64,
    fallback: &[f32],
    fallback_poses: &[DMat4],
    agents: Option<&AgentPixels>,
) -> Result<(Vec<f32>, Vec<f32>, Vec<bool>)> {
    let hw = size.0 * size.1;
    let per = 3 * hw;
    let n = cameras.len();
    ensure!(
        r.images.len() == n * 2 * per && r.poses.len() == n,
        "reference base: {} reference values and {} poses for {n} cameras of {}x{}",
        r.images.len(),
        r.poses.len(),
        size.0,
        size.1
    );
    ensure!(
        fallback.len() == n * per && fallback_poses.len() == n,
        "reference base: a fallback of {} values and {} poses for {n} cameras",
        fallback.len(),
        fallback_poses.len()
    );
    if let Some(a) = agents {
        let nm = a.masks.len() / (n * hw).max(1);
        ensure!(
            a.masks.len() == n * nm * hw && nm >= BoxClass::ALL.len() && a.refs.len() == n,
            "reference base: {} mask values and agents of {} references for {n} cameras",
            a.masks.len(),
            a.refs.len()
        );
        ensure!(
            a.refs.iter().flatten().all(|m| m.len() == hw),
            "reference base: reference agent masks are not {}x{}",
            size.0,
            size.1
        );
    }
    let (mut img, mut grids, mut took) = (Vec::with_capacity(n * per), vec![], vec![]);
    for (i, c) in cameras.iter().enumerate() {
        let j = reference_base_choice(c, e2g, [&r.poses[i][0], &r.poses[i][1]]);
        let g = ground_warp_grid(c, e2g, &r.poses[i][j], size, max_depth)?;
        let reached = g.chunks(2).filter(|v| v[0] != NO_SOURCE).count();
        let own = &fallback[i * per..(i + 1) * per];
        let own_grid = || ground_warp_grid(c, e2g, &fallback_poses[i], size, max_depth);
        if (reached as f64) < MIN_REFERENCE_COVERAGE * hw as f64 {
            img.extend_from_slice(own);
            grids.extend(own_grid()?);
            took.push(false);
            continue;
        }
        took.push(true);
        let reference = &r.images[(2 * i + j) * per..(2 * i + j + 1) * per];
        let Some(a) = agents else {
            img.extend_from_slice(reference);
            grids.extend(g);
            continue;
        };
        // the reference's agents go where its warped pixels go; the current ones are where the layout puts them
        let logged: Vec<f32> = a.refs[i][j].iter().map(|&b| b as u8 as f32).collect();
        let logged = warp(&logged, &g, 1, size);
        let nm = a.masks.len() / (n * hw);
        let cur = &a.masks[i * nm * hw..(i * nm + BoxClass::ALL.len()) * hw];
        let held: Vec<bool> = (0..hw)
            .map(|p| logged[p] > 0.0 || (0..BoxClass::ALL.len()).any(|ch| cur[ch * hw + p] > 0.5))
            .collect();
        let held = dilate(&held, size, AGENT_MARGIN_PX);
        let (rw, fw) = (
            warp(reference, &g, 3, size),
            warp(own, &own_grid()?, 3, size),
        );
        img.extend((0..per).map(|k| if held[k % hw] { fw[k] } else { rw[k] }));
        grids.extend(std::iter::repeat_n(NO_SOURCE, hw * 2));
    }
    Ok((img, grids, took))
}

/// The agents a "composite" model needs ([`reference_agents`]); None for the other sources.
pub fn agents_for(
    source: PrevSource,
    sc: &Scenario,
    cameras: &[Camera],
    r: &Retrieved,
    size: (usize, usize),
) -> Result<Option<Vec<[Vec<bool>; 2]>>> {
    if source != PrevSource::Composite {
        return Ok(None);
    }
    reference_agents(sc, cameras, r, size).map(Some)
}
