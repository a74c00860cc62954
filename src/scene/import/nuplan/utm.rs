//! WGS84 longitude / latitude -> UTM (the devkit's `to_crs(projectedCoordSystem)` for maps stored in EPSG:4326):
//! the transverse Mercator projection by Krüger's series in the third flattening (to n^6; sub-millimetre within a
//! zone), k0 = 0.9996, false easting 500 km, false northing 10 000 km south of the equator.
use anyhow::{bail, Result};
use glam::DVec2;

/// WGS84 semi-major axis (m) and flattening.
pub const WGS84_A: f64 = 6_378_137.0;
pub const WGS84_F: f64 = 1.0 / 298.257_223_563;

/// A UTM zone.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Zone {
    pub number: u32,
    pub south: bool,
}

impl Zone {
    /// Parses a CRS string as the `meta` layer stores it: `epsg:326NN` / `EPSG:327NN`, or a PROJ string with
    /// `+proj=utm +zone=NN [+south]`. None when it is not a WGS84 UTM zone.
    pub fn parse(crs: &str) -> Option<Zone> {
        let s = crs.trim().to_ascii_lowercase();
        if let Some(code) = s.strip_prefix("epsg:") {
            let c: u32 = code.trim().parse().ok()?;
            return match c {
                32601..=32660 => Some(Zone {
                    number: c - 32600,
                    south: false,
                }),
                32701..=32760 => Some(Zone {
                    number: c - 32700,
                    south: true,
                }),
                _ => None,
            };
        }
        if s.contains("+proj=utm") {
            let z = s
                .split_whitespace()
                .find_map(|t| t.strip_prefix("+zone="))?
                .parse()
                .ok()?;
            if (1..=60).contains(&z) {
                return Some(Zone {
                    number: z,
                    south: s.split_whitespace().any(|t| t == "+south"),
                });
            }
        }
        None
    }

    /// The EPSG code of the zone.
    pub fn epsg(&self) -> u32 {
        if self.south {
            32700 + self.number
        } else {
            32600 + self.number
        }
    }

    /// Central meridian (degrees).
    pub fn lon0(&self) -> f64 {
        self.number as f64 * 6.0 - 183.0
    }
}

/// Projects (longitude, latitude) in degrees into the zone (easting, northing) in metres.
pub fn project(zone: &Zone, lon_lat: DVec2) -> Result<DVec2> {
    let (lon, lat) = (lon_lat.x, lon_lat.y);
    if !(lat.abs() <= 90.0 && lon.abs() <= 360.0 && lon.is_finite()) {
        bail!("({lon}, {lat}) is not a longitude / latitude in degrees");
    }
    Ok(
        transverse_mercator(WGS84_A, WGS84_F, 0.9996, zone.lon0(), lon, lat)
            + DVec2::new(500_000.0, if zone.south { 10_000_000.0 } else { 0.0 }),
    )
}

/// Transverse Mercator (x, y) of (lon, lat) degrees about central meridian `lon0` on ellipsoid (a, f), scale k0.
pub fn transverse_mercator(a: f64, f: f64, k0: f64, lon0: f64, lon: f64, lat: f64) -> DVec2 {
    let n = f / (2.0 - f);
    let (n2, n3) = (n * n, n * n * n);
    let (n4, n5, n6) = (n2 * n2, n2 * n3, n3 * n3);
    let big_a = a / (1.0 + n) * (1.0 + n2 / 4.0 + n4 / 64.0 + n6 / 256.0);
    let alpha = [
        n / 2.0 - 2.0 * n2 / 3.0 + 5.0 * n3 / 16.0 + 41.0 * n4 / 180.0 - 127.0 * n5 / 288.0
            + 7891.0 * n6 / 37800.0,
        13.0 * n2 / 48.0 - 3.0 * n3 / 5.0 + 557.0 * n4 / 1440.0 + 281.0 * n5 / 630.0
            - 1983433.0 * n6 / 1935360.0,
        61.0 * n3 / 240.0 - 103.0 * n4 / 140.0 + 15061.0 * n5 / 26880.0 + 167603.0 * n6 / 181440.0,
        49561.0 * n4 / 161280.0 - 179.0 * n5 / 168.0 + 6601661.0 * n6 / 7257600.0,
        34729.0 * n5 / 80640.0 - 3418889.0 * n6 / 1995840.0,
        212378941.0 * n6 / 319334400.0,
    ];
    let e = (f * (2.0 - f)).sqrt();
    let phi = lat.to_radians();
    let mut dl = (lon - lon0).to_radians();
    dl = (dl + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI;
    // Conformal latitude.
    let t = (phi.sin().atanh() - e * (e * phi.sin()).atanh()).sinh();
    let xi_p = t.atan2(dl.cos());
    let eta_p = (dl.sin() / (1.0 + t * t).sqrt()).atanh();
    let (mut xi, mut eta) = (xi_p, eta_p);
    for (j, al) in alpha.iter().enumerate() {
        let k = 2.0 * (j + 1) as f64;
        xi += al * (k * xi_p).sin() * (k * eta_p).cosh();
        eta += al * (k * xi_p).cos() * (k * eta_p).sinh();
    }
    DVec2::new(k0 * big_a * eta, k0 * big_a * xi)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zone_strings() {
        assert_eq!(
            Zone::parse("epsg:32611"),
            Some(Zone {
                number: 11,
                south: false
            })
        );
        assert_eq!(Zone::parse("EPSG:32748").unwrap().epsg(), 32748);
        let z = Zone::parse("+proj=utm +zone=19 +datum=WGS84 +units=m +no_defs").unwrap();
        assert_eq!((z.number, z.south, z.lon0()), (19, false, -69.0));
        assert!(Zone::parse("+proj=utm +zone=48 +south").unwrap().south);
        assert_eq!(Zone::parse("epsg:4326"), None);
    }

    #[test]
    fn meridian_arc_and_published_point() {
        // On the central meridian the northing is k0 times the meridian arc: 10 001 965.729 m to the pole and
        // 4 984 944.378 m to 45 degrees on WGS84.
        let z = Zone {
            number: 11,
            south: false,
        };
        let p = project(&z, DVec2::new(-117.0, 45.0)).unwrap();
        assert!((p.x - 500_000.0).abs() < 1e-6);
        assert!((p.y - 0.9996 * 4_984_944.378).abs() < 0.01, "{p}");
        let pole = project(&z, DVec2::new(-117.0, 90.0)).unwrap();
        assert!((pole.y - 0.9996 * 10_001_965.729).abs() < 0.01, "{pole}");
        // The CN Tower (43 38' 33.24" N, 79 23' 13.7" W) is at 17T 630084 E 4833438 N (rounded to metres).
        let z17 = Zone::parse("epsg:32617").unwrap();
        let lat = 43.0 + 38.0 / 60.0 + 33.24 / 3600.0;
        let lon = -(79.0 + 23.0 / 60.0 + 13.7 / 3600.0);
        let p = project(&z17, DVec2::new(lon, lat)).unwrap();
        assert!(
            (p.x - 630_084.0).abs() < 1.0 && (p.y - 4_833_438.0).abs() < 1.0,
            "{p}"
        );
        // Southern zones add the false northing; east / west of the meridian is symmetric.
        let s = project(
            &Zone {
                number: 11,
                south: true,
            },
            DVec2::new(-116.0, -10.0),
        )
        .unwrap();
        let w = project(
            &Zone {
                number: 11,
                south: true,
            },
            DVec2::new(-118.0, -10.0),
        )
        .unwrap();
        assert!(s.y < 10_000_000.0 && (s.y - w.y).abs() < 1e-6);
        assert!(((s.x - 500_000.0) + (w.x - 500_000.0)).abs() < 1e-6);
    }
}
