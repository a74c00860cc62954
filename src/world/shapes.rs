//! Solids of the ground-truth world: convex planar faces with a lit colour, grouped into solids with a bounding
//! sphere (for culling), a semantic class and an instance id. Builders for oriented boxes and n-gon frusta.
//!
//! Invariant: every solid is convex and closed or a union of such parts whose faces have outward normals, so
//! back-face culling (`n . (p - eye) >= 0`) never drops a visible face.
use super::palette::{Palette, Rgb, SemanticClass};
use glam::{DVec2, DVec3};

/// A window grid on a facade, in face coordinates: `s` metres along `s_axis` from `origin`, `t` metres up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Windows {
    pub origin: DVec3,
    pub s_axis: DVec3,
    /// Face width (m) along `s_axis` and height (m).
    pub width: f64,
    pub height: f64,
    /// Column and floor spacing (m).
    pub col: f64,
    pub floor: f64,
    /// Window size as fractions of the spacing.
    pub frac_s: f64,
    pub frac_t: f64,
    /// Lit window colour.
    pub glass: Rgb,
}

impl Windows {
    /// Whether face point `(s, t)` is glass.
    #[inline]
    pub fn is_glass(&self, s: f64, t: f64) -> bool {
        if s < 0.6 || s > self.width - 0.6 || t < 1.2 || t > self.height - 0.8 {
            return false;
        }
        let fs = (s / self.col).fract();
        let ft = (t / self.floor).fract();
        (fs - 0.5).abs() < 0.5 * self.frac_s && (ft - 0.55).abs() < 0.5 * self.frac_t
    }
}

/// One convex planar face (vertices in order around it, global frame).
#[derive(Clone, Debug, PartialEq)]
pub struct Face {
    pub pts: Vec<DVec3>,
    /// Outward unit normal.
    pub normal: DVec3,
    /// Lit colour.
    pub colour: Rgb,
    pub windows: Option<Windows>,
}

/// A solid: faces plus culling bounds and ids.
#[derive(Clone, Debug, PartialEq)]
pub struct Solid {
    pub faces: Vec<Face>,
    pub centre: DVec3,
    pub radius: f64,
    pub class: SemanticClass,
    /// 0 for scenery; objects: track index + 1.
    pub instance: u32,
}

impl Solid {
    pub fn new(class: SemanticClass, instance: u32) -> Self {
        Solid {
            faces: Vec::new(),
            centre: DVec3::ZERO,
            radius: 0.0,
            class,
            instance,
        }
    }

    /// Recomputes the bounding sphere (centre of the vertex bounds, radius to the farthest vertex).
    pub fn finish(mut self) -> Self {
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for f in &self.faces {
            for p in &f.pts {
                lo = lo.min(*p);
                hi = hi.max(*p);
            }
        }
        if self.faces.is_empty() {
            return self;
        }
        self.centre = (lo + hi) * 0.5;
        self.radius = self
            .faces
            .iter()
            .flat_map(|f| f.pts.iter())
            .map(|p| p.distance(self.centre))
            .fold(0.0, f64::max);
        self
    }
}

fn scale(c: Rgb, k: f32) -> Rgb {
    [
        (c[0] * k).min(1.0),
        (c[1] * k).min(1.0),
        (c[2] * k).min(1.0),
    ]
}

/// Local (forward, left) -> global offset for a heading.
#[inline]
fn rot(yaw: f64, v: DVec2) -> DVec2 {
    let (s, c) = yaw.sin_cos();
    DVec2::new(c * v.x - s * v.y, s * v.x + c * v.y)
}

/// Colours of a box: top, sides (the four vertical faces: front, left, rear, right), bottom.
#[derive(Clone, Copy, Debug)]
pub struct BoxColours {
    pub top: Rgb,
    pub front: Rgb,
    pub side: Rgb,
    pub rear: Rgb,
}

impl BoxColours {
    pub fn uniform(c: Rgb) -> Self {
        BoxColours {
            top: c,
            front: c,
            side: c,
            rear: c,
        }
    }
}

/// Appends the faces of an oriented box: centre `c` (x, y) at local offset `off` (forward, left) from it,
/// footprint `len x wid`, from height `z0` to `z1`, heading `yaw`. Returns the range of the new faces.
#[allow(clippy::too_many_arguments)]
pub fn push_box(
    solid: &mut Solid,
    pal: &Palette,
    c: DVec2,
    yaw: f64,
    off: DVec2,
    len: f64,
    wid: f64,
    z0: f64,
    z1: f64,
    col: BoxColours,
) -> std::ops::Range<usize> {
    let start = solid.faces.len();
    let ctr = c + rot(yaw, off);
    let (l, w) = (len * 0.5, wid * 0.5);
    // Footprint corners counter-clockwise: front-left, rear-left, rear-right, front-right.
    let fp = [
        DVec2::new(l, w),
        DVec2::new(-l, w),
        DVec2::new(-l, -w),
        DVec2::new(l, -w),
    ]
    .map(|v| ctr + rot(yaw, v));
    let up = |p: DVec2, z: f64| DVec3::new(p.x, p.y, z);
    let push = |s: &mut Solid, pts: Vec<DVec3>, n: DVec3, colour: Rgb| {
        s.faces.push(Face {
            pts,
            normal: n,
            colour: scale(colour, pal.light(n)),
            windows: None,
        })
    };
    push(
        solid,
        fp.iter().map(|p| up(*p, z1)).collect(),
        DVec3::Z,
        col.top,
    );
    push(
        solid,
        fp.iter().rev().map(|p| up(*p, z0)).collect(),
        -DVec3::Z,
        col.side,
    );
    // Side faces: edge i -> i+1 of the footprint; outward normal = edge direction rotated clockwise.
    let cols = [col.side, col.rear, col.side, col.front];
    for i in 0..4 {
        let (a, b) = (fp[i], fp[(i + 1) % 4]);
        let d = (b - a).normalize_or_zero();
        let n = DVec3::new(d.y, -d.x, 0.0);
        push(
            solid,
            vec![up(a, z0), up(b, z0), up(b, z1), up(a, z1)],
            n,
            cols[i],
        );
    }
    start..solid.faces.len()
}

/// Appends a regular `n`-gon frustum around `c`: radius `r0` at `z0`, `r1` at `z1` (convex, `n >= 3`).
#[allow(clippy::too_many_arguments)]
pub fn push_frustum(
    solid: &mut Solid,
    pal: &Palette,
    c: DVec2,
    yaw: f64,
    n: usize,
    r0: f64,
    r1: f64,
    z0: f64,
    z1: f64,
    colour: Rgb,
) {
    let n = n.max(3);
    let ring = |r: f64, z: f64| -> Vec<DVec3> {
        (0..n)
            .map(|i| {
                let a = yaw + i as f64 * std::f64::consts::TAU / n as f64;
                DVec3::new(c.x + r * a.cos(), c.y + r * a.sin(), z)
            })
            .collect()
    };
    let (lo, hi) = (ring(r0, z0), ring(r1, z1));
    let mut push = |pts: Vec<DVec3>, nrm: DVec3| {
        solid.faces.push(Face {
            pts,
            normal: nrm,
            colour: scale(colour, pal.light(nrm)),
            windows: None,
        })
    };
    if r1 > 1e-6 {
        push(hi.clone(), DVec3::Z);
    }
    push(lo.iter().rev().copied().collect(), -DVec3::Z);
    for i in 0..n {
        let j = (i + 1) % n;
        let e = hi[i] - lo[i];
        let t = lo[j] - lo[i];
        let nrm = t.cross(e).normalize_or_zero();
        let mut pts = vec![lo[i], lo[j], hi[j]];
        if r1 > 1e-6 {
            pts.push(hi[i]);
        }
        push(pts, nrm);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::import::DayPalette;

    /// Every face normal points away from the solid's centre (back-face culling relies on it).
    #[test]
    fn normals_point_outward() {
        let pal = Palette::of(DayPalette::Noon);
        let mut s = Solid::new(SemanticClass::Vehicle, 1);
        push_box(
            &mut s,
            &pal,
            DVec2::new(3.0, -2.0),
            0.7,
            DVec2::new(0.5, 0.2),
            4.0,
            2.0,
            0.2,
            1.5,
            BoxColours::uniform([0.5; 3]),
        );
        push_frustum(
            &mut s,
            &pal,
            DVec2::new(3.0, -2.0),
            0.3,
            7,
            1.0,
            0.4,
            1.5,
            3.0,
            [0.5; 3],
        );
        let s = s.finish();
        assert_eq!(s.faces.len(), 6 + 9);
        for (i, f) in s.faces.iter().enumerate() {
            let c = f.pts.iter().copied().sum::<DVec3>() / f.pts.len() as f64;
            let inner = if i < 6 {
                DVec3::new(
                    3.0 + 0.5 * 0.7f64.cos() - 0.2 * 0.7f64.sin(),
                    -2.0 + 0.5 * 0.7f64.sin() + 0.2 * 0.7f64.cos(),
                    0.85,
                )
            } else {
                DVec3::new(3.0, -2.0, 2.25)
            };
            assert!(f.normal.dot(c - inner) > 0.0, "{f:?}");
            assert!((f.normal.length() - 1.0).abs() < 1e-9);
        }
        assert!(s.radius > 2.0);
    }
}
