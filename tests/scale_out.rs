//! Scale-out (spec loop.md 3): `--shard K/N` deals the name-ordered scenarios round-robin, `b2dr merge` of the
//! shards equals the single run (CLS, per-metric means, every scenario's entry, bit for bit; only timings
//! differ), a killed shard resumes to the same merge, merges of different configurations / incomplete shard
//! sets are refused with the cause named, and the scheduler's GPU (CUDA_VISIBLE_DEVICES /
//! NVIDIA_VISIBLE_DEVICES, ordinal or UUID) picks the Vulkan device.
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use b2dr::eval::batch::{self, Shard};
use b2dr::eval::run::{run, RendererMode, RunConfig};
use b2dr::scene::import::resolve;
use b2dr::sim::AgentMode;
use b2dr::vk::{scheduler_pin, DeviceId, Pin, NVIDIA_VENDOR_ID};
use serde_json::Value;

/// Six short built-in scenarios, listed out of name order.
const SCENARIOS: &str =
    "builtin:town:0,builtin:cross:0,builtin:straight:1,builtin:curve:0,builtin:town:1,builtin:tjunction:0";
const STEPS: &str = "150";

fn b2dr() -> Command {
    Command::new(env!("CARGO_BIN_EXE_b2dr"))
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("b2dr_scale_{}_{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn ok(o: Output) -> Output {
    assert!(
        o.status.success(),
        "b2dr failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

fn sim_cmd(out: &Path, shard: Option<&str>, planner: &str) -> Command {
    let mut c = b2dr();
    c.args(["sim", "--scenario", SCENARIOS, "--planner", planner])
        .args(["--steps", STEPS, "--bev-every", "0", "--out"])
        .arg(out);
    if let Some(s) = shard {
        c.args(["--shard", s]);
    }
    c
}

fn read(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

/// A summary without what differs between two runs of one configuration: wall times, stage timings, the
/// list of merged shards.
fn deterministic(mut v: Value) -> Value {
    let o = v.as_object_mut().unwrap();
    for k in ["timing_ms", "merged_from", "device_bytes"] {
        o.remove(k);
    }
    for s in o["scenarios"].as_array_mut().unwrap() {
        let s = s.as_object_mut().unwrap();
        for k in ["wall_ms", "timing_ms", "timing_per_frame"] {
            s.remove(k);
        }
    }
    v
}

fn assert_same_results(single: &Value, merged: &Value) {
    assert_eq!(
        single["cls"].as_f64().unwrap().to_bits(),
        merged["cls"].as_f64().unwrap().to_bits(),
        "CLS differs: {} vs {}",
        single["cls"],
        merged["cls"]
    );
    let (a, b) = (deterministic(single.clone()), deterministic(merged.clone()));
    assert_eq!(
        serde_json::to_string_pretty(&a).unwrap(),
        serde_json::to_string_pretty(&b).unwrap()
    );
}

fn merge_cli(dirs: &[PathBuf], out: &Path) -> Output {
    b2dr()
        .arg("merge")
        .args(dirs)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn shard_flag_parses_and_refuses_bad_values() {
    let s: Shard = "2/3".parse().unwrap();
    assert_eq!((s.index, s.count), (2, 3));
    assert_eq!(s.to_string(), "2/3");
    for bad in ["4/3", "3/3", "0/0", "x/3", "1/y", "3", "-1/3", ""] {
        let e = format!("{:#}", bad.parse::<Shard>().unwrap_err());
        assert!(e.contains("--shard"), "{bad}: {e}");
    }
    // through the CLI: an error naming the flag, no panic
    for bad in ["4/3", "0/0", "a/b"] {
        let o = sim_cmd(&tmp("bad"), Some(bad), "expert").output().unwrap();
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && e.contains("--shard"), "{bad}: {e}");
        assert!(!e.contains("panicked"), "{e}");
    }
}

#[test]
fn shards_deal_the_sorted_list_round_robin() {
    let names = |shard| -> Vec<String> {
        batch::select(resolve(SCENARIOS).unwrap(), shard)
            .unwrap()
            .iter()
            .map(|s| s.name())
            .collect()
    };
    let all = names(None);
    let mut sorted = all.clone();
    sorted.sort();
    assert_eq!(all, sorted);
    let parts: Vec<Vec<String>> = (0..3)
        .map(|k| names(Some(Shard { index: k, count: 3 })))
        .collect();
    assert_eq!(parts[0], [all[0].clone(), all[3].clone()]);
    assert_eq!(parts[1], [all[1].clone(), all[4].clone()]);
    assert_eq!(parts[2], [all[2].clone(), all[5].clone()]);
    // more shards than scenarios: the last ones are empty
    assert!(names(Some(Shard { index: 7, count: 8 })).is_empty());
    // one folder per scenario: a scenario listed twice is refused
    let e = batch::select(resolve("builtin:town:0,builtin:town:0").unwrap(), None).unwrap_err();
    assert!(format!("{e:#}").contains("twice"), "{e:#}");
}

/// Plain processes, N = 3 in parallel; then a killed shard resumed; both merges equal the single run.
#[test]
fn sim_shards_merge_to_the_single_run_and_a_killed_shard_resumes() {
    let root = tmp("sim");
    let t0 = Instant::now();
    ok(sim_cmd(&root.join("single"), None, "expert")
        .output()
        .unwrap());
    let single = read(&root.join("single/metrics.json"));
    let t_single = t0.elapsed();
    let t0 = Instant::now();
    let dirs: Vec<PathBuf> = (0..3).map(|k| root.join(format!("shard-{k}"))).collect();
    let children: Vec<_> = (0..3)
        .map(|k| {
            sim_cmd(&dirs[k], Some(&format!("{k}/3")), "expert")
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for c in children {
        ok(c.wait_with_output().unwrap());
    }
    let t_shards = t0.elapsed();
    eprintln!("single run {t_single:?}, 3 shards in parallel {t_shards:?}");
    for (k, d) in dirs.iter().enumerate() {
        assert_eq!(
            read(&d.join("metrics.json"))["scenarios"]
                .as_array()
                .unwrap()
                .len(),
            2
        );
        assert_eq!(read(&d.join("config.json"))["shard"]["index"], k);
    }
    ok(merge_cli(&dirs, &root.join("merged")));
    let merged = read(&root.join("merged/metrics.json"));
    assert_same_results(&single, &merged);
    assert_eq!(merged["scenarios"].as_array().unwrap().len(), 6);
    assert_eq!(merged["merged_from"].as_array().unwrap().len(), 3);
    for k in batch::METRICS {
        assert!(merged["metric_means"][k].is_number(), "{k}");
    }
    assert!(merged["timing_ms"]["wall"].as_f64().unwrap() > 0.0);
    assert!(read(&root.join("merged/config.json"))
        .get("shard")
        .is_none());

    // kill shard 1 once its first scenario is done (or, if it was faster than the poll, remove what a kill
    // would have left undone), then check merge refuses it and a --resume rerun completes it
    let d1 = root.join("killed-1");
    let names: Vec<String> = batch::select(
        resolve(SCENARIOS).unwrap(),
        Some(Shard { index: 1, count: 3 }),
    )
    .unwrap()
    .iter()
    .map(|s| s.name())
    .collect();
    let first_done = d1.join(&names[0]).join("metrics.json");
    let second_done = d1.join(&names[1]).join("metrics.json");
    let mut child = sim_cmd(&d1, Some("1/3"), "expert")
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    while !first_done.is_file() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().ok();
    child.wait().unwrap();
    assert!(first_done.is_file());
    if d1.join("metrics.json").is_file() {
        eprintln!(
            "the shard finished before the kill; removing its second scenario and summary instead"
        );
        std::fs::remove_file(d1.join("metrics.json")).unwrap();
        std::fs::remove_file(&second_done).unwrap();
    } else {
        eprintln!(
            "killed the shard after its first scenario (second done: {})",
            second_done.is_file()
        );
    }
    let with_killed = [dirs[0].clone(), d1.clone(), dirs[2].clone()];
    let o = merge_cli(&with_killed, &root.join("merged-killed"));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("unfinished"), "{e}");
    let first_bytes = std::fs::read(&first_done).unwrap();
    let killed = !d1.join("metrics.json").is_file() && !second_done.is_file();
    let o = ok(sim_cmd(&d1, Some("1/3"), "expert")
        .arg("--resume")
        .output()
        .unwrap());
    // the killed run's lock was released by the system and is reported as stale (issue #36)
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!killed || e.contains("stale lock"), "{e}");
    // the finished scenario was not rerun (same bytes, wall time included)
    assert_eq!(std::fs::read(&first_done).unwrap(), first_bytes);
    ok(merge_cli(&with_killed, &root.join("merged-killed")));
    assert_same_results(&single, &read(&root.join("merged-killed/metrics.json")));
    // a requeued shard with other flags is refused
    let o = sim_cmd(&d1, Some("1/3"), "cv")
        .arg("--resume")
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("planner"), "{e}");
    std::fs::remove_dir_all(&root).ok();
}

#[test]
fn merge_refuses_other_configurations_and_incomplete_shard_sets() {
    let root = tmp("refuse");
    let run_shard = |name: &str, shard: &str, planner: &str, agents: &str| -> PathBuf {
        let d = root.join(name);
        ok(b2dr()
            .args(["sim", "--scenario", "builtin:town:0,builtin:cross:0"])
            .args(["--planner", planner, "--agents", agents, "--steps", "10"])
            .args(["--bev-every", "0", "--shard", shard, "--out"])
            .arg(&d)
            .output()
            .unwrap());
        d
    };
    let a0 = run_shard("a0", "0/2", "expert", "idm");
    let a1 = run_shard("a1", "1/2", "expert", "idm");
    let cv1 = run_shard("cv1", "1/2", "cv", "idm");
    let rep1 = run_shard("rep1", "1/2", "expert", "replay");
    let b1 = run_shard("b1", "1/3", "expert", "idm");
    let expect_err = |dirs: &[&PathBuf], words: &[&str]| {
        let o = b2dr()
            .arg("merge")
            .args(dirs)
            .arg("--out")
            .arg(root.join("m"))
            .output()
            .unwrap();
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "merge of {dirs:?} succeeded");
        assert!(!e.contains("panicked"), "{e}");
        for w in words {
            assert!(e.contains(w), "expected {w:?} in: {e}");
        }
    };
    expect_err(&[&a0, &cv1], &["different configurations", "planner"]);
    expect_err(&[&a0, &rep1], &["different configurations", "agents"]);
    expect_err(&[&a0, &b1], &["cut into 2 shards"]);
    expect_err(&[&a0], &["missing", "1/2"]);
    expect_err(&[&a0, &a0], &["twice"]);
    expect_err(&[&a0, &root.join("nowhere")], &["config.json"]);
    expect_err(&[&a0, &a1, &a1], &["twice"]);
    // shard 0's results under shard 1's name: its scenario would count twice
    let fake1 = root.join("fake1");
    std::fs::create_dir_all(&fake1).unwrap();
    let mut c = read(&a0.join("config.json"));
    c["shard"]["index"] = 1.into();
    std::fs::write(fake1.join("config.json"), c.to_string()).unwrap();
    std::fs::copy(a0.join("metrics.json"), fake1.join("metrics.json")).unwrap();
    // (refused as foreign to shard 1 before it could count twice: issue #36)
    expect_err(&[&a0, &fake1], &["cross-0", "foreign"]);
    ok(merge_cli(&[a1.clone(), a0.clone()], &root.join("m")));
    expect_err(&[&a0, &a1, &a0], &["twice"]);
    // --out must be a new folder, not a shard
    let o = merge_cli(&[a0.clone(), a1.clone()], &a0);
    assert!(!o.status.success());
    std::fs::remove_dir_all(&root).ok();
}

fn run_cfg(renderer: RendererMode, shard: Option<Shard>) -> RunConfig {
    RunConfig {
        scenario: "builtin:town:2,builtin:cross:1,builtin:straight:0".into(),
        renderer,
        model: None,
        planner: "expert".parse().unwrap(),
        agents: AgentMode::Idm,
        controller: b2dr::sim::closed_loop::Controller::Lqr,
        steps: 15,
        planner_timeout_s: 30.0,
        planner_start_timeout_s: 300.0,
        cameras: vec!["CAM_FRONT".into()],
        size: (28, 52),
        seed: 0,
        dtype: b2dr::tensor::DType::F32,
        gif: false,
        shard,
        requests: Default::default(),
    }
}

/// `b2dr run` with the exact renderer of the synthetic world: 3 shards merge to the single run, and shards
/// of another renderer are refused.
#[test]
fn run_shards_merge_to_the_single_run_and_renderers_do_not_mix() {
    let root = tmp("run");
    let single = run(
        None,
        &run_cfg(RendererMode::Groundtruth, None),
        &root.join("single"),
        false,
    )
    .unwrap();
    let dirs: Vec<PathBuf> = (0..3).map(|k| root.join(format!("gt-{k}"))).collect();
    for (k, d) in dirs.iter().enumerate() {
        let s = run(
            None,
            &run_cfg(
                RendererMode::Groundtruth,
                Some(Shard { index: k, count: 3 }),
            ),
            d,
            false,
        )
        .unwrap();
        assert_eq!(s["scenarios"].as_array().unwrap().len(), 1);
    }
    // the per-scenario folders hold the frames the planner saw
    assert!(
        std::fs::read_dir(dirs[0].join("cross-1/frames"))
            .unwrap()
            .count()
            > 0
    );
    let merged = batch::merge(&dirs, &root.join("merged")).unwrap();
    assert_same_results(&single, &merged);
    assert_eq!(read(&root.join("merged/metrics.json")), merged);
    // a shard of the boxes-only renderer does not merge with ground-truth shards
    let none1 = root.join("none-1");
    run(
        None,
        &run_cfg(RendererMode::None, Some(Shard { index: 1, count: 3 })),
        &none1,
        false,
    )
    .unwrap();
    let e = format!(
        "{:#}",
        batch::merge(&[dirs[0].clone(), none1, dirs[2].clone()], &root.join("m2")).unwrap_err()
    );
    assert!(
        e.contains("different configurations") && e.contains("renderer"),
        "{e}"
    );
    std::fs::remove_dir_all(&root).ok();
}

fn dev(vendor_id: u32, uuid_byte: u8, bus: u32) -> DeviceId {
    DeviceId {
        vendor_id,
        uuid: [uuid_byte; 16],
        pci: Some([0, bus, 0, 0]),
    }
}

#[test]
fn the_schedulers_gpu_picks_the_vulkan_device() {
    // enumeration order is not PCI order: NVIDIA GPUs on buses 0x41, 0x01, 0x81, then lavapipe
    let devices = [
        dev(NVIDIA_VENDOR_ID, 0xaa, 0x41),
        dev(NVIDIA_VENDOR_ID, 0xbb, 0x01),
        dev(NVIDIA_VENDOR_ID, 0xcc, 0x81),
        DeviceId {
            vendor_id: 0x10005,
            uuid: [0x11; 16],
            pci: None,
        },
    ];
    let pin = |var: &str, val: &str| {
        let (var, val) = (var.to_string(), val.to_string());
        scheduler_pin(&devices, &move |v| (v == var).then(|| val.clone()))
    };
    let at = |p: Pin| match p {
        Pin::Device(i, _) => i,
        other => panic!("{other:?}"),
    };
    assert_eq!(scheduler_pin(&devices, &|_| None).unwrap(), Pin::Unpinned);
    // ordinals count NVIDIA devices in PCI order
    assert_eq!(at(pin("CUDA_VISIBLE_DEVICES", "0").unwrap()), 1);
    assert_eq!(at(pin("CUDA_VISIBLE_DEVICES", "1").unwrap()), 0);
    assert_eq!(at(pin("CUDA_VISIBLE_DEVICES", "2,0").unwrap()), 2);
    assert_eq!(at(pin("NVIDIA_VISIBLE_DEVICES", "1").unwrap()), 0);
    // UUIDs, with or without the GPU- prefix, any case
    let cc = devices[2].uuid_string();
    assert!(cc.starts_with("GPU-cccccccc-cccc-"), "{cc}");
    assert_eq!(at(pin("CUDA_VISIBLE_DEVICES", &cc).unwrap()), 2);
    assert_eq!(
        at(pin("NVIDIA_VISIBLE_DEVICES", &cc[4..].to_uppercase()).unwrap()),
        2
    );
    assert_eq!(
        at(pin("CUDA_VISIBLE_DEVICES", &devices[3].uuid_string()).unwrap()),
        3
    );
    // CUDA_VISIBLE_DEVICES wins over NVIDIA_VISIBLE_DEVICES
    let both = scheduler_pin(&devices, &|v| match v {
        "CUDA_VISIBLE_DEVICES" => Some("2".into()),
        "NVIDIA_VISIBLE_DEVICES" => Some("0".into()),
        _ => None,
    })
    .unwrap();
    assert_eq!(at(both), 2);
    // no GPU assigned / all of them
    for v in ["", "none", "void", "-1", "NoDevFiles"] {
        assert!(
            matches!(pin("CUDA_VISIBLE_DEVICES", v).unwrap(), Pin::NoGpu(_)),
            "{v:?}"
        );
    }
    assert_eq!(pin("NVIDIA_VISIBLE_DEVICES", "all").unwrap(), Pin::Unpinned);
    // errors name the variable
    for (v, word) in [
        ("7", "ordinal 7"),
        (
            "GPU-00000000-0000-0000-0000-000000000000",
            "no Vulkan device has UUID",
        ),
        ("MIG-1234", "MIG"),
        ("GPU-xyz", "neither"),
    ] {
        let e = format!("{:#}", pin("CUDA_VISIBLE_DEVICES", v).unwrap_err());
        assert!(
            e.contains("CUDA_VISIBLE_DEVICES") && e.contains(word),
            "{v}: {e}"
        );
    }
    // a container / cgroup that shows only the assigned GPU: host ordinal 5, one NVIDIA device visible
    let one = [dev(NVIDIA_VENDOR_ID, 0xdd, 0x81)];
    let p = scheduler_pin(&one, &|v| {
        (v == "NVIDIA_VISIBLE_DEVICES").then(|| "5".into())
    })
    .unwrap();
    assert_eq!(at(p), 0);
    // no NVIDIA device at all (no Vulkan driver in the container): a clear error
    let e = scheduler_pin(&devices[3..], &|v| {
        (v == "CUDA_VISIBLE_DEVICES").then(|| "0".into())
    })
    .unwrap_err();
    assert!(
        format!("{e:#}").contains("NVIDIA_DRIVER_CAPABILITIES"),
        "{e:#}"
    );
}

/// `b2dr info` shows every device's UUID and follows the scheduler's variables (on lavapipe: its UUID picks
/// it, an ordinal of a GPU that is not there is a clear error, an empty list keeps to non-NVIDIA devices).
#[test]
fn info_shows_uuids_and_follows_the_scheduler() {
    let o = b2dr()
        .arg("info")
        .env_remove("CUDA_VISIBLE_DEVICES")
        .env_remove("NVIDIA_VISIBLE_DEVICES")
        .env_remove("B2DR_DEVICE")
        .output()
        .unwrap();
    if !o.status.success() {
        eprintln!(
            "SKIP: no Vulkan device ({})",
            String::from_utf8_lossy(&o.stderr)
        );
        return;
    }
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    let chosen_uuid = text
        .lines()
        .find_map(|l| l.trim().strip_prefix("uuid:"))
        .map(|u| u.trim().to_string())
        .expect(&text);
    assert!(text.contains("      uuid "), "{text}");
    assert!(
        text.contains("chosen by:") && text.contains("default"),
        "{text}"
    );
    let o = ok(b2dr()
        .arg("info")
        .env("CUDA_VISIBLE_DEVICES", &chosen_uuid)
        .env_remove("B2DR_DEVICE")
        .output()
        .unwrap());
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(
        t.contains(&format!(
            "chosen by:                  CUDA_VISIBLE_DEVICES={chosen_uuid}"
        )),
        "{t}"
    );
    let o = b2dr()
        .arg("info")
        .env(
            "CUDA_VISIBLE_DEVICES",
            "GPU-00000000-0000-0000-0000-000000000000",
        )
        .env_remove("B2DR_DEVICE")
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("CUDA_VISIBLE_DEVICES"),
        "{e}"
    );
    assert!(!e.contains("panicked"), "{e}");
    // --device still wins over the scheduler's variable
    ok(b2dr()
        .args(["--device", "0", "info"])
        .env(
            "CUDA_VISIBLE_DEVICES",
            "GPU-00000000-0000-0000-0000-000000000000",
        )
        .output()
        .unwrap());
}

// ---------------------------------------------------------------------------------- issue #36: trust nothing

fn sim_at(out: &Path, scenarios: &str, planner: &str) -> Command {
    let mut c = b2dr();
    c.args(["sim", "--scenario", scenarios, "--planner", planner])
        .args(["--steps", "10", "--bev-every", "0", "--out"])
        .arg(out);
    c
}

/// One writer per output folder (issue #36, item 1): a second `sim` on a folder a live run holds is refused,
/// naming the holder's pid; after that run is killed, the next run reports the stale lock and goes on.
#[test]
fn one_writer_per_out_folder_and_stale_locks_are_taken_over() {
    let root = tmp("lock");
    let d = root.join("out");
    // a planner that never answers holds the folder for a minute
    let mut first = sim_at(&d, "builtin:straight:1", "cmd:sleep 60")
        .args(["--planner-timeout", "60"])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    while !d.join("config.json").is_file() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    let o = sim_at(&d, "builtin:straight:1", "expert").output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr).to_string();
    let holder = first.id();
    first.kill().ok();
    first.wait().unwrap();
    assert!(
        !o.status.success()
            && e.contains("in use by another b2dr run")
            && e.contains(&format!("pid {holder}")),
        "{e}"
    );
    let o = ok(sim_at(&d, "builtin:straight:1", "expert").output().unwrap());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("stale lock") && e.contains(&format!("pid {holder}")),
        "{e}"
    );
    // a run that ends releases the lock: the next one finds nothing stale
    let o = ok(sim_at(&d, "builtin:straight:1", "expert").output().unwrap());
    assert!(!String::from_utf8_lossy(&o.stderr).contains("stale"));
    std::fs::remove_dir_all(&root).ok();
}

/// `--resume` re-checks each finished record against the folder's configuration (issue #36, item 1): a record
/// of another planner copied in, or one with a score out of [0, 1], is rerun (and named), so the resumed
/// summary equals a clean run's.
#[test]
fn resume_reruns_records_of_other_configurations() {
    let root = tmp("recheck");
    let sc = "builtin:town:0,builtin:cross:0";
    let good = root.join("good");
    ok(sim_at(&good, sc, "expert").output().unwrap());
    let cv = root.join("cv");
    ok(sim_at(&cv, sc, "cv").output().unwrap());
    let names: Vec<String> = std::fs::read_dir(&good)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.path().join("metrics.json").is_file())
        .map(|e| e.file_name().to_string_lossy().to_string())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
    let d = root.join("tampered");
    ok(sim_at(&d, sc, "expert").output().unwrap());
    std::fs::copy(
        cv.join(&names[0]).join("metrics.json"),
        d.join(&names[0]).join("metrics.json"),
    )
    .unwrap();
    let p = d.join(&names[1]).join("metrics.json");
    let mut v = read(&p);
    v["score"] = 7.0.into();
    std::fs::write(&p, v.to_string()).unwrap();
    let o = ok(sim_at(&d, sc, "expert").arg("--resume").output().unwrap());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("another configuration") && e.contains("`score`"),
        "{e}"
    );
    assert_same_results(
        &read(&good.join("metrics.json")),
        &read(&d.join("metrics.json")),
    );
    std::fs::remove_dir_all(&root).ok();
}

/// `merge` verifies what it merges (issue #36, item 2): a score or metric outside [0, 1] or missing, a record of
/// another configuration, a dropped or foreign scenario, a shard summary that is not its records', totals that
/// overflow: each refused naming the shard, the scenario and the field; nothing is written.
#[test]
fn merge_verifies_scores_scenario_sets_and_totals() {
    let root = tmp("verify");
    let sc = "builtin:town:0,builtin:cross:0,builtin:straight:1,builtin:curve:0";
    let shard = |name: &str, k: usize, planner: &str| {
        let d = root.join(name);
        ok(sim_at(&d, sc, planner)
            .args(["--shard", &format!("{k}/2")])
            .output()
            .unwrap());
        d
    };
    let a0 = shard("a0", 0, "expert");
    let a1 = shard("a1", 1, "expert");
    let cv1 = shard("cv1", 1, "cv");
    ok(merge_cli(&[a0.clone(), a1.clone()], &root.join("m")));
    // a copy of a1 whose summary is edited by `edit`
    let n = std::cell::Cell::new(0);
    let tampered = |edit: &dyn Fn(&mut Value)| {
        n.set(n.get() + 1);
        let t = root.join(format!("t{}", n.get()));
        std::fs::create_dir_all(&t).unwrap();
        std::fs::copy(a1.join("config.json"), t.join("config.json")).unwrap();
        let mut v = read(&a1.join("metrics.json"));
        edit(&mut v);
        std::fs::write(t.join("metrics.json"), v.to_string()).unwrap();
        t
    };
    let refused = |t: &PathBuf, words: &[&str]| {
        let out = root.join("m-bad");
        let o = merge_cli(&[a0.clone(), t.clone()], &out);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "merge with {t:?} succeeded");
        for w in words {
            assert!(e.contains(w), "expected {w:?} in: {e}");
        }
        assert!(!out.join("metrics.json").exists());
    };
    let first = |v: &Value| v["scenarios"][0]["scenario"].as_str().unwrap().to_string();
    let s0 = first(&read(&a1.join("metrics.json")));
    let t = tampered(&|v| v["scenarios"][0]["score"] = 1.5.into());
    refused(&t, &[&t.display().to_string(), &s0, "`score`"]);
    let t = tampered(&|v| v["scenarios"][0]["score"] = Value::Null);
    refused(&t, &[&s0, "`score`"]);
    let t = tampered(&|v| v["scenarios"][0]["metrics"]["ego_is_comfortable"] = (-0.1).into());
    refused(&t, &[&s0, "metrics.ego_is_comfortable"]);
    let cv_rec = read(&cv1.join("metrics.json"))["scenarios"][0].clone();
    let t = tampered(&|v| v["scenarios"][0] = cv_rec.clone());
    refused(&t, &[&s0, "another configuration"]);
    let t = tampered(&|v| {
        v["scenarios"].as_array_mut().unwrap().remove(0);
    });
    refused(&t, &[&s0, "dropped"]);
    let t = tampered(&|v| {
        let mut x = v["scenarios"][0].clone();
        x["scenario"] = "elsewhere-9".into();
        v["scenarios"].as_array_mut().unwrap().push(x);
    });
    refused(&t, &["elsewhere-9", "foreign"]);
    let t = tampered(&|v| v["cls"] = 0.123.into());
    refused(&t, &["`cls`"]);
    let t = tampered(&|v| {
        for s in v["scenarios"].as_array_mut().unwrap() {
            s["wall_ms"] = 1.5e308.into();
        }
    });
    refused(&t, &["timing_ms.wall"]);
    std::fs::remove_dir_all(&root).ok();
}
