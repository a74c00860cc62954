//! Criterion benches of every op case in `b2dr::ops::bench` (the same cases `b2dr bench ops` prints).
//! Each iteration replays a recorded command buffer and waits for its fence before the clock is read.
use b2dr::ops::bench;
use b2dr::vk::{Context, ContextOptions};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};

fn ops(c: &mut Criterion) {
    let ctx = match Context::new(&ContextOptions::default()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("SKIP: no Vulkan device ({e:#})");
            return;
        }
    };
    let mut g = c.benchmark_group("ops");
    g.sample_size(10);
    for case in bench::cases() {
        let rec = (case.build)(&ctx).expect("build case");
        g.throughput(Throughput::Elements(case.flops as u64));
        g.bench_function(&case.name, |b| {
            b.iter(|| rec.submit_wait().expect("submit"))
        });
    }
    g.finish();
}

criterion_group!(benches, ops);
criterion_main!(benches);
