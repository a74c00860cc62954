//! The scene's objects as solids: each object's shapes lie inside its 3D box (gravity centre at z = height / 2,
//! the convention of `projection::scene`), so its pixels fall inside its projected box mask.
//!
//! Vehicles: a body over the full footprint, a shorter and narrower cabin on top (glass sides, body-coloured
//! roof), four dark wheels; per-track colour. Pedestrians: legs, torso, head. Cyclists: two wheels, a frame, a
//! rider. Cones: an orange frustum on a base plate. Barriers: a red-and-white block.
use super::palette::{hash_bytes, Palette, Rgb, SemanticClass, CLOTHES, VEHICLE_COLOURS};
use super::shapes::{push_box, push_frustum, BoxColours, Solid};
use crate::projection::scene::track_geometry;
use crate::scene::{ObjectClass, Scenario};
use glam::{DVec2, DVec3};

/// One object of a scene state.
#[derive(Clone, Debug, PartialEq)]
pub struct WorldObject {
    /// Track index (the instance id is `track + 1`).
    pub track: usize,
    pub class: ObjectClass,
    /// Gravity centre (global).
    pub center: DVec3,
    /// (length, width, height).
    pub size: DVec3,
    pub yaw: f64,
    /// Colour seed (the hash of the track id).
    pub look: u64,
}

/// The objects of `sc` observed at log step `k`.
pub fn objects_at(sc: &Scenario, k: usize) -> Vec<WorldObject> {
    sc.tracks
        .iter()
        .enumerate()
        .filter_map(|(i, t)| {
            let s = t.states.get(k).copied().flatten()?;
            let (center, size) = track_geometry(t, &s);
            Some(WorldObject {
                track: i,
                class: t.class,
                center,
                size,
                yaw: s.pose.heading,
                look: hash_bytes(t.id.as_bytes()),
            })
        })
        .collect()
}

pub fn semantic_class(c: ObjectClass) -> SemanticClass {
    match c {
        ObjectClass::Vehicle => SemanticClass::Vehicle,
        ObjectClass::Pedestrian => SemanticClass::Pedestrian,
        ObjectClass::Bicycle => SemanticClass::Bicycle,
        ObjectClass::TrafficCone => SemanticClass::TrafficCone,
        ObjectClass::Barrier => SemanticClass::Barrier,
        ObjectClass::CzoneSign | ObjectClass::GenericObject => SemanticClass::OtherObject,
    }
}

fn darker(c: Rgb, k: f32) -> Rgb {
    [c[0] * k, c[1] * k, c[2] * k]
}

/// The solid of one object.
pub fn object_solid(o: &WorldObject, pal: &Palette) -> Solid {
    let mut s = Solid::new(semantic_class(o.class), o.track as u32 + 1);
    let c = o.center.truncate();
    let (l, w, h) = (o.size.x, o.size.y, o.size.z);
    let y = o.yaw;
    let pick = |table: &[Rgb], salt: u64| table[((o.look ^ salt) % table.len() as u64) as usize];
    match o.class {
        ObjectClass::Vehicle => {
            let body = pick(&VEHICLE_COLOURS, 0);
            let tyre: Rgb = [0.06, 0.06, 0.07];
            let glass: Rgb = [0.28, 0.34, 0.42];
            let wheel_r = (0.22 * h).clamp(0.25, 0.4);
            let (z_body, z_belt) = (wheel_r * 0.9, h * 0.58);
            // The body stops 3 cm short of the box ends, so the lamps in front of it are not coplanar with it.
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l - 0.06,
                w,
                z_body,
                z_belt,
                BoxColours {
                    top: body,
                    front: darker(body, 0.92),
                    side: body,
                    rear: darker(body, 0.85),
                },
            );
            // Cabin: glass all round, slightly behind the centre, body-coloured roof.
            let cab_l = l * 0.58;
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::new(-l * 0.06, 0.0),
                cab_l,
                w * 0.9,
                z_belt,
                h,
                BoxColours {
                    top: body,
                    front: glass,
                    side: glass,
                    rear: glass,
                },
            );
            // Pillars/roof edge line: a thin body-coloured band under the roof.
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::new(-l * 0.06, 0.0),
                cab_l,
                w * 0.92,
                h * 0.93,
                h,
                BoxColours::uniform(body),
            );
            for (fx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                let off = DVec2::new(fx * (l * 0.5 - wheel_r * 1.5), sy * (w * 0.5 - 0.14));
                push_box(
                    &mut s,
                    pal,
                    c,
                    y,
                    off,
                    wheel_r * 2.0,
                    0.28,
                    0.0,
                    wheel_r * 2.0,
                    BoxColours::uniform(tyre),
                );
            }
            // Lights: a light front band and a red rear band just outside the body (still inside the box).
            let lamp_z = (z_belt - 0.22, z_belt - 0.08);
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::new(l * 0.5 - 0.02, 0.0),
                0.04,
                w * 0.9,
                lamp_z.0,
                lamp_z.1,
                BoxColours::uniform([0.95, 0.93, 0.80]),
            );
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::new(-l * 0.5 + 0.02, 0.0),
                0.04,
                w * 0.9,
                lamp_z.0,
                lamp_z.1,
                BoxColours::uniform([0.75, 0.05, 0.05]),
            );
        }
        ObjectClass::Pedestrian => {
            let shirt = pick(&CLOTHES, 1);
            let trousers = darker(pick(&CLOTHES, 7), 0.6);
            let skin: Rgb = [0.80, 0.62, 0.50];
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l * 0.75,
                w * 0.85,
                0.0,
                h * 0.5,
                BoxColours::uniform(trousers),
            );
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l * 0.9,
                w,
                h * 0.5,
                h * 0.84,
                BoxColours::uniform(shirt),
            );
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l * 0.55,
                w * 0.55,
                h * 0.84,
                h,
                BoxColours::uniform(skin),
            );
        }
        ObjectClass::Bicycle => {
            let tyre: Rgb = [0.08, 0.08, 0.09];
            let frame = pick(&CLOTHES, 3);
            let shirt = pick(&CLOTHES, 5);
            let r = (0.22 * h).min(l * 0.25);
            for fx in [1.0, -1.0] {
                push_box(
                    &mut s,
                    pal,
                    c,
                    y,
                    DVec2::new(fx * (l * 0.5 - r), 0.0),
                    2.0 * r,
                    w * 0.3,
                    0.0,
                    2.0 * r,
                    BoxColours::uniform(tyre),
                );
            }
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l - 2.0 * r,
                w * 0.3,
                r * 0.6,
                r * 2.0,
                BoxColours::uniform(frame),
            );
            // Rider: legs from the pedals up, torso, head.
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::new(-l * 0.05, 0.0),
                l * 0.55,
                w * 0.8,
                r,
                h * 0.57,
                BoxColours::uniform(darker(shirt, 0.5)),
            );
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::new(0.0, 0.0),
                l * 0.55,
                w * 0.95,
                h * 0.57,
                h * 0.86,
                BoxColours::uniform(shirt),
            );
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::new(l * 0.05, 0.0),
                l * 0.18,
                w * 0.45,
                h * 0.86,
                h,
                BoxColours::uniform([0.80, 0.62, 0.50]),
            );
        }
        ObjectClass::TrafficCone => {
            let orange: Rgb = [0.95, 0.42, 0.08];
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l,
                w,
                0.0,
                h * 0.08,
                BoxColours::uniform([0.15, 0.15, 0.15]),
            );
            let r = l.min(w) * 0.5;
            push_frustum(
                &mut s,
                pal,
                c,
                y + std::f64::consts::FRAC_PI_4,
                4,
                r * std::f64::consts::SQRT_2,
                r * 0.35,
                h * 0.08,
                h,
                orange,
            );
        }
        ObjectClass::Barrier => {
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l,
                w,
                0.0,
                h * 0.5,
                BoxColours::uniform([0.85, 0.85, 0.85]),
            );
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l,
                w,
                h * 0.5,
                h,
                BoxColours::uniform([0.80, 0.12, 0.10]),
            );
        }
        ObjectClass::CzoneSign | ObjectClass::GenericObject => {
            push_box(
                &mut s,
                pal,
                c,
                y,
                DVec2::ZERO,
                l,
                w,
                0.0,
                h,
                BoxColours::uniform([0.5, 0.5, 0.5]),
            );
        }
    }
    s.finish()
}
