//! Ground-truth renderer benchmark: all six cameras of the nuScenes-like rig at 224 x 400 (and 112 x 200), one
//! thread, full scenery and the objects of the log step. `cargo bench --bench world`.
//! - `world_6cam_224x400_town0_step{40,100}`: the figure to keep under 100 ms (issue #13).
//! - `world_6cam_112x200_town0_step40`: the training-size render.
//! - `world_scenery_build_town0`: building the static world of a scenario (once per scenario).
use b2dr::scene::import::ego2global;
use b2dr::world::{load_all, Scenery, World};
use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let sc = load_all("builtin:town:0").unwrap().remove(0);
    let world = World::new(&sc);
    for (step, h, w) in [
        (40usize, 224usize, 400usize),
        (100, 224, 400),
        (40, 112, 200),
    ] {
        let e2g = ego2global(&sc.ego[step].rear_axle);
        c.bench_function(&format!("world_6cam_{h}x{w}_town0_step{step}"), |b| {
            b.iter(|| {
                black_box(
                    world
                        .render_step(&sc.rig.cameras, &e2g, step, w, h, 1)
                        .unwrap(),
                )
            })
        });
    }
    c.bench_function("world_scenery_build_town0", |b| {
        b.iter(|| {
            black_box(Scenery::build(
                &sc,
                b2dr::world::Palette::of(b2dr::world::palette_of(&sc)),
            ))
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
