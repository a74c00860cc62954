//! The activation workspace's lifetime check: in debug builds, recording an op that reads a tensor after the
//! workspace released its buffer (and before it is handed out again) is an error naming the op and buffer.
mod common;

use b2dr::nn::device::Workspace;
use b2dr::ops::elementwise;
use b2dr::tensor::DType;

#[test]
fn read_after_release_is_refused_in_debug_builds() {
    let Some(ctx) = common::ctx() else { return };
    let mut ws = Workspace::new(&ctx, DType::F32);
    let x = common::upload(&ctx, &[4, 8], DType::F32, &common::uniform(32, 1.0, 1));
    let a = ws.alloc(&[4, 8]).unwrap();
    let out = ws.alloc(&[4, 8]).unwrap();
    let mut rec = ctx.recorder().unwrap();
    elementwise::silu(&mut rec, &x, &a).unwrap();
    // `a` is still read below: releasing it here is the bug the check catches
    let stale = a.clone();
    ws.release(a);
    let r = elementwise::silu(&mut rec, &stale, &out);
    if cfg!(debug_assertions) {
        let e = format!(
            "{:#}",
            r.expect_err("a read of a released buffer must be refused")
        );
        assert!(e.contains("released"), "{e}");
    } else {
        // release builds record it unchecked
        r.unwrap();
    }
    // handed out again, the buffer is usable
    let b = ws.alloc(&[4, 8]).unwrap();
    assert_eq!(
        b.buffer().id(),
        stale.buffer().id(),
        "smallest fit reuses the buffer"
    );
    elementwise::silu(&mut rec, &x, &b).unwrap();
    elementwise::silu(&mut rec, &b, &out).unwrap();
    rec.finish().unwrap().submit_wait().unwrap();
    common::assert_no_validation_errors();
}

#[test]
#[cfg(debug_assertions)]
#[should_panic(expected = "released twice")]
fn double_release_panics_in_debug_builds() {
    let Some(ctx) = common::ctx() else {
        panic!("released twice (no device: nothing to check)")
    };
    let mut ws = Workspace::new(&ctx, DType::F32);
    let a = ws.alloc(&[16]).unwrap();
    ws.release(a.clone());
    ws.release(a);
}
