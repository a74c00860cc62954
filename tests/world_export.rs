//! Training export: the hierarchical reference statistics over thousands of samples (planned without
//! rendering), and a round trip of a tiny export through safetensors.
use b2dr::projection::retrieval::TRAINING_INTERVALS;
use b2dr::scene::geometry::Pose2;
use b2dr::world::export::plan::{candidate_frames, plan_samples};
use b2dr::world::export::{export_training, ExportOptions};
use b2dr::world::images::ImageStore;
use b2dr::world::load_all;
use b2dr::world::view::layout_masks;
use safetensors::SafeTensors;

/// At least 2000 samples: reference distances fall into 2-5 / 5-10 / 10-15 m with frequencies within 3 points of
/// 0.1 / 0.3 / 0.6; slot 0 is ahead and slot 1 behind unless that side has no image in the drawn interval.
#[test]
fn reference_distances_follow_the_hierarchical_bins() {
    let mut counts = [0usize; 3];
    let (mut pairs, mut one_sided) = (0usize, 0usize);
    for spec in [
        "builtin:town:0",
        "builtin:town:1",
        "builtin:tjunction:2",
        "builtin:straight:3",
        "builtin:curve:4",
        "builtin:multilane:5",
        "builtin:cross:6",
    ] {
        let sc = load_all(spec).unwrap().remove(0);
        let frames = candidate_frames(&sc);
        let plans = plan_samples(
            &sc,
            &frames,
            &sc.rig.cameras,
            1000,
            &[Pose2::default()],
            7,
            false,
        );
        assert!(plans.len() > 100, "{spec}: {} samples", plans.len());
        for p in &plans {
            assert_eq!(
                p.step - 5,
                b2dr::world::export::plan::frame_step(&sc, &frames[p.prev])
            );
            for (ci, pair) in p.refs.iter().enumerate() {
                pairs += 1;
                let cam = &sc.rig.cameras[ci].name;
                let pose = frames[p.frame].image(cam).unwrap().ego2global;
                let heading = pose.x_axis.truncate().truncate().normalize();
                let along: Vec<f64> = frames
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| *i != p.frame)
                    .map(|(_, f)| {
                        (f.ego2global.w_axis - pose.w_axis)
                            .truncate()
                            .truncate()
                            .dot(heading)
                    })
                    .collect();
                for (slot, r) in pair.iter().enumerate() {
                    let d = r.along.abs();
                    let bin = TRAINING_INTERVALS
                        .iter()
                        .position(|iv| d >= iv.0 && d < iv.1)
                        .unwrap();
                    counts[bin] += 1;
                    let want_ahead = slot == 0;
                    if (r.along > 0.0) != want_ahead {
                        one_sided += 1;
                        // Allowed only when the wanted side has no image in that interval.
                        let (lo, hi, _) = TRAINING_INTERVALS[bin];
                        assert!(
                            !along.iter().any(|&a| (a > 0.0) == want_ahead && a.abs() >= lo && a.abs() < hi),
                            "{spec} step {} {cam} slot {slot}: took the other side although its own had an image",
                            p.step
                        );
                    }
                }
            }
        }
    }
    let n: usize = counts.iter().sum();
    assert!(pairs >= 2000, "{pairs} pairs");
    for (i, c) in counts.iter().enumerate() {
        let f = *c as f64 / n as f64;
        assert!(
            (f - TRAINING_INTERVALS[i].2).abs() <= 0.03,
            "interval {i}: {f:.3} vs {} ({counts:?} of {n})",
            TRAINING_INTERVALS[i].2
        );
    }
    assert!(
        (one_sided as f64) < 0.15 * (2 * pairs) as f64,
        "{one_sided} one-sided of {}",
        2 * pairs
    );
    println!("{pairs} pairs, interval counts {counts:?}, {one_sided} one-sided references");
}

fn tensor<'a>(st: &'a SafeTensors, name: &str) -> (Vec<usize>, safetensors::Dtype, &'a [u8]) {
    let t = st.tensor(name).unwrap();
    (t.shape().to_vec(), t.dtype(), t.data())
}

fn f64s(b: &[u8]) -> Vec<f64> {
    b.chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

#[test]
fn export_round_trips_through_safetensors() {
    let dir = std::env::temp_dir().join(format!("b2dr_world_export_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (h, w) = (32usize, 56usize);
    let s = export_training(&ExportOptions {
        scenarios: vec!["builtin:town:4".into()],
        out: dir.clone(),
        height: h,
        width: w,
        samples_per_scenario: 3,
        offsets: vec![Pose2::default(), Pose2::new(0.0, 1.5, 5f64.to_radians())],
        seed: 3,
        cameras: vec!["CAM_FRONT".into(), "CAM_BACK_LEFT".into()],
        shard_samples: 4,
        progress: false,
        prev_chain: false,
    })
    .unwrap();
    assert_eq!((s.samples, s.shards), (6, 2));
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("index.json")).unwrap()).unwrap();
    let bytes = std::fs::read(dir.join("shard_00000.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (shape, dt, target) = tensor(&st, "target");
    assert_eq!((shape, dt), (vec![4, 2, 3, h, w], safetensors::Dtype::U8));
    assert_eq!(tensor(&st, "ref").0, vec![4, 2, 2, 3, h, w]);
    let (mshape, mdt, masks) = tensor(&st, "masks_packed");
    assert_eq!((mshape, mdt), (vec![4, 2, h, w], safetensors::Dtype::U16));
    assert_eq!(tensor(&st, "ego2global").0, vec![4, 2, 4, 4]);
    assert_eq!(tensor(&st, "ref_distance").1, safetensors::Dtype::F32);
    // Row 0 (unperturbed): its target is the recorded image, its masks the projection's.
    let sample0 = &index["samples"][0];
    assert_eq!(sample0["perturbed"], false);
    let step = sample0["step"].as_u64().unwrap() as usize;
    let sc = load_all("builtin:town:4").unwrap().remove(0);
    let frames = candidate_frames(&sc);
    let store = ImageStore::new(&sc, None);
    let img = frames[step].image("CAM_FRONT").unwrap();
    let px = store.image(img, w, h).unwrap();
    let n = w * h;
    for c in 0..3 {
        for p in 0..n {
            assert_eq!(target[c * n + p], px.data[3 * p + c]);
        }
    }
    let cam = sc.rig.camera("CAM_FRONT").unwrap().clone();
    let layer = b2dr::projection::scene::map_layer(&sc.map);
    let m = layout_masks(&sc, &layer, &[cam], &img.ego2global, step, w, h).unwrap();
    for p in 0..n {
        let packed = u16::from_le_bytes([masks[2 * p], masks[2 * p + 1]]);
        for ch in 0..15 {
            assert_eq!((packed >> ch) & 1, m[0].channel(ch)[p] as u16);
        }
    }
    // Row 1: the same target displaced by (0, 1.5 m, 5 deg); its pose says so, its prev/references are the log's.
    let sample1 = &index["samples"][1];
    assert_eq!(sample1["perturbed"], true);
    assert_eq!(sample1["refs"], sample0["refs"]);
    let e2g = f64s(tensor(&st, "ego2global").2);
    let (r0, r1) = (&e2g[0..16], &e2g[32..48]); // row 0 cam 0, row 1 cam 0 (row-major)
    let yaw0 = r0[4].atan2(r0[0]);
    let yaw1 = r1[4].atan2(r1[0]);
    assert!((yaw1 - yaw0 - 5f64.to_radians()).abs() < 1e-9);
    let lateral = (-yaw0.sin()) * (r1[3] - r0[3]) + yaw0.cos() * (r1[7] - r0[7]);
    assert!((lateral - 1.5).abs() < 1e-9, "{lateral}");
    let prev = f64s(tensor(&st, "prev_ego2global").2);
    assert_eq!(&prev[0..16], &prev[32..48]);
    // Without --prev-chain the chain tensors are absent.
    assert!(st.tensor("prev2").is_err() && st.tensor("prev_masks_packed").is_err());
    assert!(st.tensor("prev2_ego2global").is_err());
    assert_eq!(index["prev_chain"], false);
    std::fs::remove_dir_all(&dir).ok();
}

/// `--prev-chain`: every sample carries its previous frame's own previous image (the log's, 0.5 s before it) and
/// the previous frame's layout at its logged pose and step, for displaced samples too.
#[test]
fn prev_chain_exports_the_previous_frames_inputs() {
    let dir = std::env::temp_dir().join(format!("b2dr_world_export_chain_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (h, w) = (24usize, 40usize);
    let s = export_training(&ExportOptions {
        scenarios: vec!["builtin:tjunction:5".into()],
        out: dir.clone(),
        height: h,
        width: w,
        samples_per_scenario: 2,
        offsets: vec![Pose2::default(), Pose2::new(0.0, -1.5, 0.0)],
        seed: 1,
        cameras: vec!["CAM_FRONT_LEFT".into(), "CAM_FRONT".into()],
        shard_samples: 64,
        progress: false,
        prev_chain: true,
    })
    .unwrap();
    assert_eq!((s.samples, s.shards), (4, 1));
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("index.json")).unwrap()).unwrap();
    assert_eq!(index["prev_chain"], true);
    let bytes = std::fs::read(dir.join("shard_00000.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    assert_eq!(tensor(&st, "prev2").0, vec![4, 2, 3, h, w]);
    let (mshape, mdt, pmasks) = tensor(&st, "prev_masks_packed");
    assert_eq!((mshape, mdt), (vec![4, 2, h, w], safetensors::Dtype::U16));
    let p2 = tensor(&st, "prev2").2;
    let prev_e2g = f64s(tensor(&st, "prev_ego2global").2);
    let (p2shape, p2dt, p2e2g) = tensor(&st, "prev2_ego2global");
    assert_eq!((p2shape, p2dt), (vec![4, 2, 4, 4], safetensors::Dtype::F64));
    let prev2_e2g = f64s(p2e2g);
    let sc = load_all("builtin:tjunction:5").unwrap().remove(0);
    let frames = candidate_frames(&sc);
    let store = ImageStore::new(&sc, None);
    let layer = b2dr::projection::scene::map_layer(&sc.map);
    let n = w * h;
    for (row, sample) in index["samples"].as_array().unwrap().iter().enumerate() {
        let (step, prev_step) = (
            sample["step"].as_u64().unwrap(),
            sample["prev_step"].as_u64().unwrap(),
        );
        let prev2_step = sample["prev2_step"].as_u64().unwrap() as usize;
        assert_eq!(
            (step - prev_step, prev_step as usize - prev2_step),
            (5, 5),
            "row {row}"
        );
        for (ci, cam_name) in ["CAM_FRONT_LEFT", "CAM_FRONT"].iter().enumerate() {
            let off = (row * 2 + ci) * 3 * n;
            let img = frames[prev2_step].image(cam_name).unwrap();
            // its pose: the log's (the chain's first hop warps it to the previous frame's pose)
            let want = img.ego2global.transpose().to_cols_array();
            let p2e = &prev2_e2g[(row * 2 + ci) * 16..(row * 2 + ci + 1) * 16];
            assert_eq!(p2e, &want[..], "row {row} {cam_name}: prev2 pose");
            let px = store.image(img, w, h).unwrap();
            for c in 0..3 {
                for p in 0..n {
                    assert_eq!(
                        p2[off + c * n + p],
                        px.data[3 * p + c],
                        "row {row} {cam_name}"
                    );
                }
            }
            // the previous frame's layout at the pose the file holds for it (the log's)
            let pimg = frames[prev_step as usize].image(cam_name).unwrap();
            let pe = &prev_e2g[(row * 2 + ci) * 16..(row * 2 + ci + 1) * 16];
            let want = pimg.ego2global.transpose().to_cols_array();
            assert_eq!(pe, &want[..], "row {row} {cam_name}: prev pose");
            let cam = sc.rig.camera(cam_name).unwrap().clone();
            let m = layout_masks(
                &sc,
                &layer,
                &[cam],
                &pimg.ego2global,
                prev_step as usize,
                w,
                h,
            )
            .unwrap();
            let moff = (row * 2 + ci) * n * 2;
            let mut drivable = 0;
            for p in 0..n {
                let b = moff + 2 * p;
                let packed = u16::from_le_bytes([pmasks[b], pmasks[b + 1]]);
                for ch in 0..15 {
                    assert_eq!(
                        (packed >> ch) & 1,
                        m[0].channel(ch)[p] as u16,
                        "row {row} {cam_name} ch {ch}"
                    );
                }
                drivable += (packed >> 10) & 1;
            }
            if ci == 1 {
                assert!(
                    drivable > 0,
                    "row {row}: the front camera's previous layout shows no road"
                );
            }
        }
    }
    // the displaced row shares its previous frame's inputs with the logged row of the same target
    let m = tensor(&st, "prev_masks_packed").2;
    let one = 2 * n * 2;
    assert_eq!(&m[0..one], &m[one..2 * one]);
    std::fs::remove_dir_all(&dir).ok();
}
