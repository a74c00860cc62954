//! `b2dr world` and `b2dr export-training` on good and bad input: bad input is a clear error (exit status 1
//! with a message naming the problem), never a panic (status 101).
use std::process::Command;

fn b2dr(args: &[&str]) -> (i32, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_b2dr"))
        .args(args)
        .output()
        .expect("running b2dr");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr),
    )
}

#[test]
fn world_writes_images_and_rejects_bad_input() {
    let dir = std::env::temp_dir().join(format!("b2dr_world_cli_{}", std::process::id()));
    let d = dir.to_str().unwrap();
    let (code, msg) = b2dr(&[
        "world",
        "--scenario",
        "builtin:curve:1",
        "--step",
        "30",
        "--offset",
        "0,-1,3",
        "--size",
        "56x100",
        "--out",
        d,
    ]);
    assert_eq!(code, 0, "{msg}");
    for f in [
        "mosaic.png",
        "bev.png",
        "overlay_mosaic.png",
        "CAM_FRONT.png",
        "CAM_BACK_overlay.png",
        "CAM_FRONT_class.png",
        "CAM_FRONT_depth.png",
    ] {
        let img = image::open(dir.join(f)).unwrap();
        assert!(img.width() > 0, "{f}");
    }
    let bad: [(&[&str], &str); 9] = [
        (&["--cameras", "CAM_NOPE"], "unknown camera"),
        (&["--step", "5000"], "out of range"),
        (&["--offset", "0,80,0"], "off the map"),
        (&["--offset", "1,2"], "DX,DY,DYAW"),
        (&["--offset", "a,b,c"], "not a finite number"),
        (&["--size", "0x400"], "8..=4096"),
        (&["--size", "224"], "HEIGHTxWIDTH"),
        (&["--size", "axb"], "not an integer"),
        (
            &["--scenario", "builtin:nowhere"],
            "unknown builtin scenario",
        ),
    ];
    for (extra, want) in bad {
        let mut args = vec!["world", "--out", d];
        if !extra.contains(&"--scenario") {
            args.extend_from_slice(&["--scenario", "builtin:town"]);
        }
        args.extend_from_slice(extra);
        let (code, msg) = b2dr(&args);
        assert_eq!(code, 1, "{extra:?}: {msg}");
        assert!(msg.contains(want), "{extra:?}: {msg}");
        assert!(!msg.contains("panicked"), "{msg}");
    }
    let (code, msg) = b2dr(&[
        "export-training",
        "--scenario",
        "builtin:town",
        "--out",
        d,
        "--size",
        "9999x3",
    ]);
    assert_eq!(code, 1, "{msg}");
    let (code, msg) = b2dr(&[
        "export-training",
        "--scenario",
        "builtin:town",
        "--out",
        d,
        "--offsets",
        "0,0",
    ]);
    assert!(code == 1 && msg.contains("DX,DY,DYAW"), "{msg}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Determinism across runs: two processes write byte-identical images.
#[test]
fn world_images_are_identical_across_runs() {
    let base = std::env::temp_dir().join(format!("b2dr_world_runs_{}", std::process::id()));
    let mut bytes = Vec::new();
    for run in 0..2 {
        let d = base.join(run.to_string());
        let (code, msg) = b2dr(&[
            "world",
            "--scenario",
            "builtin:multilane:2::morning",
            "--step",
            "77",
            "--size",
            "224x400",
            "--out",
            d.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{msg}");
        bytes.push(
            ["mosaic.png", "CAM_FRONT_class.png", "bev.png"]
                .map(|f| std::fs::read(d.join(f)).unwrap()),
        );
    }
    assert!(bytes[0] == bytes[1], "images differ between runs");
    std::fs::remove_dir_all(&base).ok();
}
