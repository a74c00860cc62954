//! The protocol-v2 JSON fixture both sides' tests read (tests/fixtures/planner_v2_session.json: what `b2dr run
//! --scenario builtin:town --renderer groundtruth --steps 6 --command-def nuscenes --history 4` sent a planner,
//! recorded by python/tests/fixtures/record_planner.py; the Python planner package's tests parse it) is still
//! what b2dr sends: the `start` message, each `plan` message's fields and every camera entry's calibration. A
//! failure means the wire format changed: re-record the fixture (the command in record_planner.py) and check
//! the package's parser (python/b2dr_planner/records.py).
mod common;

use std::path::PathBuf;

use b2dr::scene::geometry::Pose2;
use b2dr::scene::import::{ego2global, resolve};
use b2dr::sim::external::{camera_entry, start_message};
use b2dr::sim::lidar::ego_in_lidar;
use serde_json::Value;

fn fixture() -> Value {
    let p =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/planner_v2_session.json");
    serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap()
}

/// Every number of `a` within `tol` of `b`'s, the rest equal (`what` names the place).
fn assert_close(a: &Value, b: &Value, tol: f64, what: &str) {
    match (a, b) {
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{what}: lengths");
            for (i, (p, q)) in x.iter().zip(y).enumerate() {
                assert_close(p, q, tol, &format!("{what}[{i}]"));
            }
        }
        (Value::Object(x), Value::Object(y)) => {
            let keys = |o: &serde_json::Map<String, Value>| o.keys().cloned().collect::<Vec<_>>();
            assert_eq!(keys(x), keys(y), "{what}: fields");
            for (k, v) in x {
                assert_close(v, &y[k], tol, &format!("{what}.{k}"));
            }
        }
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= tol, "{what}: {x} vs {y}");
        }
        _ => assert_eq!(a, b, "{what}"),
    }
}

#[test]
fn the_recorded_start_message_is_what_b2dr_sends() {
    let sc = b2dr::world::load(&resolve("builtin:town").unwrap()[0]).unwrap();
    assert_close(&start_message(&sc), &fixture()["start"], 0.0, "start");
}

#[test]
fn the_recorded_plan_messages_are_what_b2dr_sends() {
    let sc = b2dr::world::load(&resolve("builtin:town").unwrap()[0]).unwrap();
    let fx = fixture();
    let plans = fx["plans"].as_array().unwrap();
    assert_eq!(plans.len(), 2);
    let mut keys: Vec<&str> = plans[0]
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    keys.sort();
    // the fields of a version-2 `plan` request (src/sim/external.rs plan_request, docs/planner_protocol.md)
    assert_eq!(
        keys,
        [
            "cameras",
            "command",
            "command_def",
            "ego",
            "ego_in_lidar",
            "history",
            "images",
            "inline_bytes",
            "reply",
            "route",
            "scenario",
            "step",
            "time_s",
            "type",
            "version"
        ]
    );
    let l2e = sc.rig.lidar2ego;
    let rows = |m: &glam::DMat4| serde_json::json!([0, 1, 2, 3].map(|r| m.row(r).to_array()));
    for plan in plans {
        assert_close(
            &plan["ego_in_lidar"],
            &rows(&ego_in_lidar(&l2e)),
            1e-12,
            "ego_in_lidar",
        );
        let e = &plan["ego"];
        let pose = Pose2::new(
            e["x"].as_f64().unwrap(),
            e["y"].as_f64().unwrap(),
            e["heading"].as_f64().unwrap(),
        );
        let e2g = ego2global(&pose);
        let cams = plan["cameras"].as_array().unwrap();
        assert_eq!(cams.len(), sc.rig.cameras.len());
        for c in cams {
            let cam = sc
                .rig
                .cameras
                .iter()
                .find(|r| r.name == c["camera"].as_str().unwrap())
                .unwrap();
            let (w, h) = (
                c["width"].as_u64().unwrap() as u32,
                c["height"].as_u64().unwrap() as u32,
            );
            let frame = common::frame_without_pixels(cam, e2g, w, h);
            let mut want = camera_entry(&frame, &e2g, &l2e);
            // the recorded pixels' checksum is the renderer's; this frame has none
            want["fnv1a64"] = c["fnv1a64"].clone();
            assert_close(
                c,
                &want,
                1e-9,
                &format!("step {} {}", plan["step"], cam.name),
            );
        }
    }
}
