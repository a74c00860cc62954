//! GeoPackage geometry blobs: the GPKG header (magic `GP`, version, flags with byte order, envelope kind and
//! empty bit, srs_id, optional envelope of 4, 6 or 8 doubles) followed by WKB (ISO or EWKB-style Z/M flags):
//! Point, LineString, Polygon, MultiPoint, MultiLineString, MultiPolygon, GeometryCollection. Only x and y are
//! kept.
use anyhow::{anyhow, bail, Result};
use glam::DVec2;

/// A 2D geometry.
#[derive(Clone, Debug, PartialEq)]
pub enum Geometry {
    Point(DVec2),
    LineString(Vec<DVec2>),
    /// Exterior ring first, then holes (closing point kept as stored).
    Polygon(Vec<Vec<DVec2>>),
    Multi(Vec<Geometry>),
    Empty,
}

impl Geometry {
    /// Every polygon in it (exterior + holes), flattening Multi*.
    pub fn polygons(&self) -> Vec<Vec<Vec<DVec2>>> {
        match self {
            Geometry::Polygon(r) => vec![r.clone()],
            Geometry::Multi(g) => g.iter().flat_map(|x| x.polygons()).collect(),
            _ => vec![],
        }
    }
    /// The geometry with every point mapped by `f`.
    pub fn try_map(&self, f: &impl Fn(DVec2) -> Result<DVec2>) -> Result<Geometry> {
        let ring = |r: &Vec<DVec2>| r.iter().map(|p| f(*p)).collect::<Result<Vec<_>>>();
        Ok(match self {
            Geometry::Point(p) => Geometry::Point(f(*p)?),
            Geometry::LineString(l) => Geometry::LineString(ring(l)?),
            Geometry::Polygon(rs) => Geometry::Polygon(rs.iter().map(ring).collect::<Result<_>>()?),
            Geometry::Multi(g) => {
                Geometry::Multi(g.iter().map(|x| x.try_map(f)).collect::<Result<_>>()?)
            }
            Geometry::Empty => Geometry::Empty,
        })
    }
    /// Every line string in it, flattening Multi*.
    pub fn lines(&self) -> Vec<Vec<DVec2>> {
        match self {
            Geometry::LineString(l) => vec![l.clone()],
            Geometry::Multi(g) => g.iter().flat_map(|x| x.lines()).collect(),
            _ => vec![],
        }
    }
}

/// Removes the closing point of a ring (the map model stores open rings).
pub fn open_ring(mut r: Vec<DVec2>) -> Vec<DVec2> {
    if r.len() > 1 && r.first() == r.last() {
        r.pop();
    }
    r
}

/// Parses a GPKG geometry blob.
pub fn parse_gpkg(blob: &[u8]) -> Result<Geometry> {
    if blob.len() < 8 || &blob[..2] != b"GP" {
        bail!("not a GeoPackage geometry (no `GP` magic)");
    }
    let flags = blob[3];
    if flags & 0x20 != 0 {
        bail!("extended GeoPackage geometries are not supported");
    }
    let env_len = match (flags >> 1) & 0x07 {
        0 => 0,
        1 => 32,
        2 | 3 => 48,
        4 => 64,
        k => bail!("GeoPackage header: invalid envelope indicator {k}"),
    };
    let start = 8 + env_len;
    if blob.len() < start {
        bail!("GeoPackage header truncated ({} bytes)", blob.len());
    }
    if flags & 0x10 != 0 && blob.len() == start {
        return Ok(Geometry::Empty);
    }
    let mut r = Reader {
        b: &blob[start..],
        i: 0,
    };
    let g = r.geometry(0)?;
    Ok(g)
}

/// Parses plain WKB.
pub fn parse_wkb(b: &[u8]) -> Result<Geometry> {
    Reader { b, i: 0 }.geometry(0)
}

struct Reader<'a> {
    b: &'a [u8],
    i: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8]> {
        let s = self.b.get(self.i..self.i + n).ok_or_else(|| {
            anyhow!(
                "WKB truncated at byte {} (needs {n} more, {} left)",
                self.i,
                self.b.len().saturating_sub(self.i)
            )
        })?;
        self.i += n;
        Ok(s)
    }
    fn u32(&mut self, le: bool) -> Result<u32> {
        let b: [u8; 4] = self.take(4)?.try_into().unwrap();
        Ok(if le {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }
    fn f64(&mut self, le: bool) -> Result<f64> {
        let b: [u8; 8] = self.take(8)?.try_into().unwrap();
        Ok(if le {
            f64::from_le_bytes(b)
        } else {
            f64::from_be_bytes(b)
        })
    }
    fn count(&mut self, le: bool, min_size: usize) -> Result<usize> {
        let n = self.u32(le)? as usize;
        if n.saturating_mul(min_size) > self.b.len().saturating_sub(self.i) {
            bail!("WKB count {n} at byte {} exceeds the data", self.i - 4);
        }
        Ok(n)
    }
    fn points(&mut self, le: bool, dims: usize) -> Result<Vec<DVec2>> {
        let n = self.count(le, 8 * dims)?;
        (0..n).map(|_| self.point(le, dims)).collect()
    }
    fn point(&mut self, le: bool, dims: usize) -> Result<DVec2> {
        let x = self.f64(le)?;
        let y = self.f64(le)?;
        for _ in 2..dims {
            self.f64(le)?;
        }
        Ok(DVec2::new(x, y))
    }
    fn geometry(&mut self, depth: usize) -> Result<Geometry> {
        if depth > 8 {
            bail!("WKB nested too deep");
        }
        let le = match self.take(1)?[0] {
            0 => false,
            1 => true,
            o => bail!(
                "WKB byte order {o} at byte {} (0 or 1 expected)",
                self.i - 1
            ),
        };
        let raw = self.u32(le)?;
        // EWKB flags (Z 0x80000000, M 0x40000000, SRID 0x20000000) or ISO offsets (1000 Z, 2000 M, 3000 ZM).
        let (mut z, mut m) = (raw & 0x8000_0000 != 0, raw & 0x4000_0000 != 0);
        if raw & 0x2000_0000 != 0 {
            self.u32(le)?; // SRID
        }
        let base = raw & 0x0fff_ffff;
        let kind = match base / 1000 {
            0 => base,
            1 => {
                z = true;
                base - 1000
            }
            2 => {
                m = true;
                base - 2000
            }
            3 => {
                (z, m) = (true, true);
                base - 3000
            }
            _ => bail!("WKB geometry type {raw} is not supported"),
        };
        let dims = 2 + usize::from(z) + usize::from(m);
        Ok(match kind {
            1 => {
                let p = self.point(le, dims)?;
                if p.x.is_nan() && p.y.is_nan() {
                    Geometry::Empty
                } else {
                    Geometry::Point(p)
                }
            }
            2 => Geometry::LineString(self.points(le, dims)?),
            3 => {
                let n = self.count(le, 4)?;
                Geometry::Polygon(
                    (0..n)
                        .map(|_| self.points(le, dims))
                        .collect::<Result<_>>()?,
                )
            }
            4..=7 => {
                let n = self.count(le, 5)?;
                Geometry::Multi(
                    (0..n)
                        .map(|_| self.geometry(depth + 1))
                        .collect::<Result<_>>()?,
                )
            }
            k => bail!("WKB geometry type {k} is not supported (1 to 7 are)"),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn le_line(pts: &[(f64, f64)]) -> Vec<u8> {
        let mut b = vec![1u8];
        b.extend(2u32.to_le_bytes());
        b.extend((pts.len() as u32).to_le_bytes());
        for (x, y) in pts {
            b.extend(x.to_le_bytes());
            b.extend(y.to_le_bytes());
        }
        b
    }

    #[test]
    fn gpkg_header_with_and_without_envelope() {
        let wkb = le_line(&[(1.0, 2.0), (3.0, 4.0)]);
        let mut a = b"GP\x00\x01".to_vec();
        a.extend(32611i32.to_le_bytes());
        a.extend(&wkb);
        let mut b = b"GP\x00\x03".to_vec();
        b.extend(32611i32.to_le_bytes());
        for v in [1.0f64, 3.0, 2.0, 4.0] {
            b.extend(v.to_le_bytes());
        }
        b.extend(&wkb);
        let want = Geometry::LineString(vec![DVec2::new(1.0, 2.0), DVec2::new(3.0, 4.0)]);
        assert_eq!(parse_gpkg(&a).unwrap(), want);
        assert_eq!(parse_gpkg(&b).unwrap(), want);
    }

    #[test]
    fn big_endian_point_z_and_multipolygon() {
        // Big-endian Point Z (ISO 1001).
        let mut p = vec![0u8];
        p.extend(1001u32.to_be_bytes());
        for v in [5.0f64, 6.0, 7.0] {
            p.extend(v.to_be_bytes());
        }
        assert_eq!(
            parse_wkb(&p).unwrap(),
            Geometry::Point(DVec2::new(5.0, 6.0))
        );
        // MultiPolygon of one square with a hole.
        let ring = |s: f64| -> Vec<u8> {
            let pts = [(0.0, 0.0), (s, 0.0), (s, s), (0.0, s), (0.0, 0.0)];
            let mut b = (pts.len() as u32).to_le_bytes().to_vec();
            for (x, y) in pts {
                b.extend(x.to_le_bytes());
                b.extend(y.to_le_bytes());
            }
            b
        };
        let mut poly = vec![1u8];
        poly.extend(3u32.to_le_bytes());
        poly.extend(2u32.to_le_bytes());
        poly.extend(ring(10.0));
        poly.extend(ring(1.0));
        let mut mp = vec![1u8];
        mp.extend(6u32.to_le_bytes());
        mp.extend(1u32.to_le_bytes());
        mp.extend(&poly);
        let g = parse_wkb(&mp).unwrap();
        let polys = g.polygons();
        assert_eq!(polys.len(), 1);
        assert_eq!(polys[0].len(), 2);
        assert_eq!(open_ring(polys[0][0].clone()).len(), 4);
    }

    #[test]
    fn corrupt_blobs_are_errors() {
        let wkb = le_line(&[(1.0, 2.0), (3.0, 4.0)]);
        assert!(parse_wkb(&wkb[..wkb.len() - 3]).is_err());
        assert!(parse_gpkg(&wkb).is_err()); // no GP magic
        let mut bad = wkb.clone();
        bad[5] = 0xff; // count 0xff...: exceeds the data
        assert!(parse_wkb(&bad).is_err());
        let mut t = wkb;
        t[1] = 99;
        assert!(parse_wkb(&t).is_err());
    }
}
