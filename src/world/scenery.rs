//! The static world of a scenario, built once per scenario: ground layers (sidewalks and kerbs along the road
//! edges, asphalt, crosswalk stripes, stop lines, lane markings) and roadside solids (buildings with a facade
//! colour and a window grid, trees, street-light poles) placed procedurally along the road edges.
//!
//! Everything is a function of the map and the scenery seed (the hash of the scenario's source string, so
//! `builtin:town:1` and `builtin:town:2` differ and one town looks different from place to place); nothing is
//! random at render time.
use super::palette::{hash_bytes, Palette, Rgb, SemanticClass, FACADE_COLOURS};
use super::shapes::{push_box, push_frustum, BoxColours, Solid, Windows};
use crate::scene::geometry::{convex_intersect, Aabb};
use crate::scene::map::Map;
use crate::scene::roadlines::{road_lines, LineKind, RoadLine};
use crate::scene::Scenario;
use glam::DVec2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// One flat polygon on the ground (z = 0), drawn in list order (later layers paint over earlier ones).
#[derive(Clone, Debug, PartialEq)]
pub struct GroundPoly {
    /// Rings (exterior and holes, even-odd).
    pub rings: Vec<Vec<DVec2>>,
    /// Unlit colour.
    pub colour: Rgb,
    pub class: SemanticClass,
    pub bounds: Aabb,
}

/// The static world.
#[derive(Clone, Debug)]
pub struct Scenery {
    pub palette: Palette,
    pub ground: Vec<GroundPoly>,
    pub solids: Vec<Solid>,
}

const KERB_W: f64 = 0.3;
const SIDEWALK_W: f64 = 3.2;
const LINE_W: f64 = 0.18;
const DASH: f64 = 3.0;
const DASH_PERIOD: f64 = 9.0;
/// Most ground polygons and roadside solids of one world: a map with far-flung roads (a 1e8 m lane of a
/// scenario file) stops being decorated there instead of placing 10^7 trees (built-in towns hold a few
/// thousand of each).
pub const MAX_GROUND: usize = 200_000;
pub const MAX_SOLIDS: usize = 50_000;
/// Most zebra bars of one crosswalk (a 1 km crossing).
const MAX_ZEBRA_BARS: usize = 1000;

/// The scenery seed of a scenario: FNV-1a of its source string and map name.
pub fn scenery_seed(sc: &Scenario) -> u64 {
    hash_bytes(format!("{}|{}", sc.source, sc.map.name).as_bytes())
}

fn poly(rings: Vec<Vec<DVec2>>, colour: Rgb, class: SemanticClass) -> Option<GroundPoly> {
    let mut b = Aabb::EMPTY;
    for r in &rings {
        for p in r {
            b.add(*p);
        }
    }
    (!b.is_empty() && rings.iter().any(|r| r.len() >= 3)).then_some(GroundPoly {
        rings,
        colour,
        class,
        bounds: b,
    })
}

/// A strip along `line` between offsets `d0` and `d1` (metres along its outward normals) over points
/// `i0..=i1`.
fn strip(line: &RoadLine, i0: usize, i1: usize, d0: f64, d1: f64) -> Vec<DVec2> {
    let mut r: Vec<DVec2> = (i0..=i1)
        .map(|i| line.points[i] + line.outward[i] * d0)
        .collect();
    r.extend(
        (i0..=i1)
            .rev()
            .map(|i| line.points[i] + line.outward[i] * d1),
    );
    r
}

/// Dashes of `line` (DASH metres every DASH_PERIOD), each a strip of the given offsets.
fn dashes(line: &RoadLine, d0: f64, d1: f64, out: &mut Vec<Vec<DVec2>>) {
    let pts = &line.points;
    let mut s = 0.0;
    let mut acc = vec![0.0];
    for w in pts.windows(2) {
        s += (w[1] - w[0]).length();
        acc.push(s);
    }
    let at = |t: f64| -> (DVec2, DVec2) {
        let i = acc.partition_point(|&a| a <= t).clamp(1, pts.len() - 1);
        let (a, b) = (acc[i - 1], acc[i]);
        let f = if b > a { (t - a) / (b - a) } else { 0.0 };
        let n =
            (line.outward[i - 1] + (line.outward[i] - line.outward[i - 1]) * f).normalize_or_zero();
        (pts[i - 1] + (pts[i] - pts[i - 1]) * f, n)
    };
    let mut t = 1.0;
    while t + DASH <= s && out.len() < MAX_GROUND {
        let (a, na) = at(t);
        let (b, nb) = at(t + DASH);
        out.push(vec![a + na * d0, b + nb * d0, b + nb * d1, a + na * d1]);
        t += DASH_PERIOD;
    }
}

/// Zebra stripes of a crosswalk: for a quadrilateral, bars 0.5 m wide every 1 m along its long axis, each
/// spanning the short axis; other shapes are painted whole.
fn zebra(pts: &[DVec2]) -> Vec<Vec<DVec2>> {
    if pts.len() != 4 {
        return vec![pts.to_vec()];
    }
    let (e0, e1) = (pts[1] - pts[0], pts[3] - pts[0]);
    let (long, short) = if e0.length() >= e1.length() {
        (e0, e1)
    } else {
        (e1, e0)
    };
    let len = long.length();
    let u = long / len.max(1e-9);
    let n = ((len / 1.0).floor() as usize).min(MAX_ZEBRA_BARS);
    let margin = (len - n as f64 * 1.0 + 0.5) * 0.5;
    (0..n)
        .map(|i| {
            let a = pts[0] + u * (margin + i as f64);
            let b = a + u * 0.5;
            vec![a, b, b + short, a + short]
        })
        .collect()
}

fn ground_layers(map: &Map, lines: &[RoadLine], pal: &Palette) -> Vec<GroundPoly> {
    let mut g = Vec::new();
    for l in lines.iter().filter(|l| l.kind == LineKind::RoadEdge) {
        let last = l.points.len() - 1;
        g.extend(poly(
            vec![strip(l, 0, last, KERB_W, KERB_W + SIDEWALK_W)],
            pal.sidewalk,
            SemanticClass::Sidewalk,
        ));
        g.extend(poly(
            vec![strip(l, 0, last, 0.0, KERB_W)],
            pal.kerb,
            SemanticClass::Kerb,
        ));
    }
    if !map.drivable.is_empty() {
        g.extend(poly(
            map.drivable.rings.clone(),
            pal.asphalt,
            SemanticClass::Road,
        ));
    }
    for l in &map.lanes {
        g.extend(poly(
            vec![l.polygon.clone()],
            pal.asphalt,
            SemanticClass::Road,
        ));
    }
    for r in &map.intersections {
        g.extend(poly(vec![r.clone()], pal.asphalt, SemanticClass::Road));
    }
    for c in &map.crosswalks {
        for bar in zebra(&c.polygon) {
            g.extend(poly(vec![bar], pal.white_paint, SemanticClass::Crosswalk));
        }
    }
    for s in &map.stop_lines {
        g.extend(poly(
            vec![s.polygon.to_vec()],
            pal.white_paint,
            SemanticClass::StopLine,
        ));
    }
    for l in lines {
        let last = l.points.len() - 1;
        let mut rings = Vec::new();
        let colour = match l.kind {
            LineKind::RoadEdge => {
                rings.push(strip(l, 0, last, -0.25 - LINE_W, -0.25));
                pal.white_paint
            }
            LineKind::CentreLine => {
                rings.push(strip(l, 0, last, -0.1 - LINE_W * 0.7, -0.1));
                rings.push(strip(l, 0, last, 0.1, 0.1 + LINE_W * 0.7));
                pal.yellow_paint
            }
            LineKind::LaneDivider => {
                dashes(l, -LINE_W * 0.5, LINE_W * 0.5, &mut rings);
                pal.white_paint
            }
        };
        for r in rings {
            g.extend(poly(vec![r], colour, SemanticClass::LaneMarking));
        }
        if g.len() >= MAX_GROUND {
            break;
        }
    }
    g.truncate(MAX_GROUND);
    g
}

/// Whether a footprint keeps `clear` metres from every road surface.
fn clear_of_roads(map: &Map, fp: &[DVec2; 4], clear: f64) -> bool {
    let c = (fp[0] + fp[2]) * 0.5;
    let mut pts: Vec<DVec2> = fp.to_vec();
    for i in 0..4 {
        pts.push((fp[i] + fp[(i + 1) % 4]) * 0.5);
    }
    pts.push(c);
    pts.iter()
        .all(|p| map.drivable_distance(*p, clear).is_infinite())
        && map.intersections.iter().all(|r| !convex_intersect(r, fp))
}

fn building(
    pal: &Palette,
    rng: &mut ChaCha8Rng,
    c: DVec2,
    yaw: f64,
    len: f64,
    depth: f64,
    height: f64,
) -> Solid {
    let mut s = Solid::new(SemanticClass::Building, 0);
    let facade = FACADE_COLOURS[rng.gen_range(0..FACADE_COLOURS.len())];
    let roof = [facade[0] * 0.7, facade[1] * 0.7, facade[2] * 0.7];
    let range = push_box(
        &mut s,
        pal,
        c,
        yaw,
        DVec2::ZERO,
        depth,
        len,
        0.0,
        height,
        BoxColours {
            top: roof,
            ..BoxColours::uniform(facade)
        },
    );
    let glass_base: Rgb = if rng.gen_bool(0.3) {
        [0.55, 0.62, 0.70]
    } else {
        [0.16, 0.20, 0.27]
    };
    let col = rng.gen_range(2.2..3.4);
    let floor = rng.gen_range(2.9..3.6);
    let (frac_s, frac_t) = (rng.gen_range(0.35..0.7), rng.gen_range(0.4..0.65));
    for f in &mut s.faces[range] {
        if f.normal.z.abs() > 0.5 {
            continue;
        }
        let (a, b) = (f.pts[0], f.pts[1]);
        let width = (b - a).truncate().length();
        let light = pal.light(f.normal);
        f.windows = Some(Windows {
            origin: a,
            s_axis: (b - a).normalize_or_zero(),
            width,
            height,
            col,
            floor,
            frac_s,
            frac_t,
            glass: glass_base.map(|v| (v * light).min(1.0)),
        });
    }
    s.finish()
}

fn tree(pal: &Palette, rng: &mut ChaCha8Rng, p: DVec2) -> Solid {
    let mut s = Solid::new(SemanticClass::Vegetation, 0);
    let h = rng.gen_range(4.0..7.0);
    let r = rng.gen_range(1.2..2.2);
    let yaw = rng.gen_range(0.0..1.0);
    push_frustum(
        &mut s,
        pal,
        p,
        yaw,
        6,
        0.15,
        0.12,
        0.0,
        h * 0.45,
        [0.36, 0.25, 0.15],
    );
    let green: Rgb = [
        rng.gen_range(0.15..0.28),
        rng.gen_range(0.38..0.52),
        rng.gen_range(0.12..0.2),
    ];
    push_frustum(&mut s, pal, p, yaw, 8, r * 0.5, r, h * 0.35, h * 0.6, green);
    push_frustum(&mut s, pal, p, yaw, 8, r, r * 0.15, h * 0.6, h, green);
    s.finish()
}

fn pole(pal: &Palette, p: DVec2, towards_road: DVec2) -> Solid {
    let mut s = Solid::new(SemanticClass::Pole, 0);
    let grey = [0.42, 0.43, 0.45];
    push_frustum(&mut s, pal, p, 0.0, 6, 0.12, 0.09, 0.0, 7.0, grey);
    let yaw = towards_road.y.atan2(towards_road.x);
    push_box(
        &mut s,
        pal,
        p,
        yaw,
        DVec2::new(0.9, 0.0),
        1.8,
        0.25,
        6.8,
        7.05,
        BoxColours::uniform(grey),
    );
    s.finish()
}

/// Places buildings, trees and poles along the road edges.
fn roadside(map: &Map, lines: &[RoadLine], pal: &Palette, seed: u64) -> Vec<Solid> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::new();
    // footprints placed so far, indexed: the overlap test of a new lot looks at its neighbours only (a scan
    // of every earlier footprint made placement quadratic in the road length)
    let mut footprints: Vec<[DVec2; 4]> = Vec::new();
    let mut footprint_index = crate::scene::index::BoxIndex::default();
    for l in lines.iter().filter(|l| l.kind == LineKind::RoadEdge) {
        if out.len() >= MAX_SOLIDS {
            break;
        }
        let pts = &l.points;
        let mut acc = vec![0.0];
        for w in pts.windows(2) {
            acc.push(acc.last().copied().unwrap_or(0.0) + (w[1] - w[0]).length());
        }
        let total = *acc.last().unwrap_or(&0.0);
        let at = |t: f64| {
            let i = acc.partition_point(|&a| a <= t).clamp(1, pts.len() - 1);
            let f = ((t - acc[i - 1]) / (acc[i] - acc[i - 1]).max(1e-9)).clamp(0.0, 1.0);
            (
                pts[i - 1] + (pts[i] - pts[i - 1]) * f,
                l.outward[i - 1].lerp(l.outward[i], f).normalize_or_zero(),
            )
        };
        // Poles and street trees on the sidewalk.
        let mut t = rng.gen_range(2.0..10.0);
        while t < total && out.len() < MAX_SOLIDS {
            let (p, n) = at(t);
            if rng.gen_bool(0.45) {
                out.push(pole(pal, p + n * (KERB_W + 0.5), -n));
            } else {
                out.push(tree(pal, &mut rng, p + n * (KERB_W + SIDEWALK_W * 0.6)));
            }
            t += rng.gen_range(11.0..24.0);
        }
        // Lots behind the sidewalk: a building or a small park.
        let mut t = rng.gen_range(0.0..6.0);
        while t < total && out.len() < MAX_SOLIDS {
            let front = rng.gen_range(8.0..20.0);
            let (p, n) = at((t + front * 0.5).min(total));
            let depth = rng.gen_range(8.0..16.0);
            let setback = KERB_W + SIDEWALK_W + rng.gen_range(0.8..4.0);
            let c = p + n * (setback + depth * 0.5);
            let yaw = n.y.atan2(n.x);
            let u = n.perp();
            let fp = [
                c + n * (depth * 0.5) + u * (front * 0.5),
                c - n * (depth * 0.5) + u * (front * 0.5),
                c - n * (depth * 0.5) - u * (front * 0.5),
                c + n * (depth * 0.5) - u * (front * 0.5),
            ];
            let free = clear_of_roads(map, &fp, KERB_W + SIDEWALK_W + 0.5) && {
                let mut hit = false;
                footprint_index.query(&Aabb::from_points(&fp), |i| {
                    hit = hit || convex_intersect(&footprints[i as usize], &fp)
                });
                !hit
            };
            if free {
                if rng.gen_bool(0.8) {
                    let height = if rng.gen_bool(0.25) {
                        rng.gen_range(14.0..30.0)
                    } else {
                        rng.gen_range(5.0..13.0)
                    };
                    out.push(building(pal, &mut rng, c, yaw, front, depth, height));
                } else {
                    for k in 0..3 {
                        let q = c + u * ((k as f64 - 1.0) * front * 0.3);
                        out.push(tree(pal, &mut rng, q));
                    }
                }
                footprint_index.insert(Aabb::from_points(&fp));
                footprints.push(fp);
            }
            t += front + rng.gen_range(1.0..5.0);
        }
    }
    out
}

impl Scenery {
    /// The static world of `sc` under palette `pal`.
    pub fn build(sc: &Scenario, pal: Palette) -> Scenery {
        let lines = road_lines(&sc.map);
        Scenery {
            ground: ground_layers(&sc.map, &lines, &pal),
            solids: {
                let mut v = roadside(&sc.map, &lines, &pal, scenery_seed(sc));
                v.truncate(MAX_SOLIDS);
                v
            },
            palette: pal,
        }
    }
}
