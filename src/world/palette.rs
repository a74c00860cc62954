//! Colours of the ground-truth world: the day palettes (sky, sun, ground tones), the semantic classes of the
//! class-id image, and the colour tables objects and buildings draw from. Colours are sRGB in [0, 1].
use crate::scene::import::DayPalette;
use glam::DVec3;

pub type Rgb = [f32; 3];

/// Per-pixel semantic class of the class-id image (`u8`). Object classes come after the static ones.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum SemanticClass {
    Sky = 0,
    Grass = 1,
    Sidewalk = 2,
    Kerb = 3,
    Road = 4,
    LaneMarking = 5,
    Crosswalk = 6,
    StopLine = 7,
    Building = 8,
    Vegetation = 9,
    Pole = 10,
    Vehicle = 11,
    Pedestrian = 12,
    Bicycle = 13,
    TrafficCone = 14,
    Barrier = 15,
    OtherObject = 16,
}

impl SemanticClass {
    pub const ALL: [SemanticClass; 17] = [
        SemanticClass::Sky,
        SemanticClass::Grass,
        SemanticClass::Sidewalk,
        SemanticClass::Kerb,
        SemanticClass::Road,
        SemanticClass::LaneMarking,
        SemanticClass::Crosswalk,
        SemanticClass::StopLine,
        SemanticClass::Building,
        SemanticClass::Vegetation,
        SemanticClass::Pole,
        SemanticClass::Vehicle,
        SemanticClass::Pedestrian,
        SemanticClass::Bicycle,
        SemanticClass::TrafficCone,
        SemanticClass::Barrier,
        SemanticClass::OtherObject,
    ];

    pub fn name(self) -> &'static str {
        match self {
            SemanticClass::Sky => "sky",
            SemanticClass::Grass => "grass",
            SemanticClass::Sidewalk => "sidewalk",
            SemanticClass::Kerb => "kerb",
            SemanticClass::Road => "road",
            SemanticClass::LaneMarking => "lane_marking",
            SemanticClass::Crosswalk => "crosswalk",
            SemanticClass::StopLine => "stop_line",
            SemanticClass::Building => "building",
            SemanticClass::Vegetation => "vegetation",
            SemanticClass::Pole => "pole",
            SemanticClass::Vehicle => "vehicle",
            SemanticClass::Pedestrian => "pedestrian",
            SemanticClass::Bicycle => "bicycle",
            SemanticClass::TrafficCone => "traffic_cone",
            SemanticClass::Barrier => "barrier",
            SemanticClass::OtherObject => "other_object",
        }
    }

    /// A distinct display colour (class-image visualisation).
    pub fn display_colour(self) -> [u8; 3] {
        const C: [[u8; 3]; 17] = [
            [70, 130, 180],
            [107, 142, 35],
            [244, 35, 232],
            [200, 200, 200],
            [128, 64, 128],
            [255, 255, 255],
            [250, 170, 30],
            [255, 0, 0],
            [70, 70, 70],
            [0, 190, 0],
            [153, 153, 153],
            [0, 0, 142],
            [220, 20, 60],
            [119, 11, 32],
            [255, 120, 0],
            [190, 153, 153],
            [100, 100, 100],
        ];
        C[self as usize]
    }
}

/// Colours and light of one day palette.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Palette {
    pub sky_zenith: Rgb,
    pub sky_horizon: Rgb,
    pub grass: Rgb,
    pub asphalt: Rgb,
    pub sidewalk: Rgb,
    pub kerb: Rgb,
    pub white_paint: Rgb,
    pub yellow_paint: Rgb,
    /// Unit vector towards the sun (global frame, z up).
    pub sun: DVec3,
    /// Ambient and diffuse weights of the Lambert term: `ambient + diffuse * max(0, n . sun)`.
    pub ambient: f32,
    pub diffuse: f32,
}

fn sun(azimuth_deg: f64, elevation_deg: f64) -> DVec3 {
    let (a, e) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    DVec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin())
}

impl Palette {
    pub fn of(p: DayPalette) -> Palette {
        match p {
            DayPalette::Noon => Palette {
                sky_zenith: [0.30, 0.52, 0.86],
                sky_horizon: [0.74, 0.84, 0.95],
                grass: [0.36, 0.52, 0.22],
                asphalt: [0.33, 0.33, 0.35],
                sidewalk: [0.66, 0.64, 0.60],
                kerb: [0.82, 0.82, 0.80],
                white_paint: [0.93, 0.93, 0.93],
                yellow_paint: [0.92, 0.76, 0.18],
                sun: sun(35.0, 62.0),
                ambient: 0.45,
                diffuse: 0.6,
            },
            DayPalette::Morning => Palette {
                sky_zenith: [0.42, 0.58, 0.85],
                sky_horizon: [0.95, 0.83, 0.70],
                grass: [0.34, 0.50, 0.25],
                asphalt: [0.36, 0.35, 0.36],
                sidewalk: [0.70, 0.65, 0.58],
                kerb: [0.84, 0.80, 0.75],
                white_paint: [0.95, 0.92, 0.88],
                yellow_paint: [0.95, 0.75, 0.20],
                sun: sun(100.0, 22.0),
                ambient: 0.42,
                diffuse: 0.65,
            },
            DayPalette::Evening => Palette {
                sky_zenith: [0.28, 0.32, 0.58],
                sky_horizon: [0.96, 0.64, 0.42],
                grass: [0.30, 0.40, 0.20],
                asphalt: [0.30, 0.28, 0.30],
                sidewalk: [0.62, 0.55, 0.50],
                kerb: [0.78, 0.70, 0.64],
                white_paint: [0.92, 0.86, 0.80],
                yellow_paint: [0.93, 0.68, 0.20],
                sun: sun(260.0, 14.0),
                ambient: 0.38,
                diffuse: 0.62,
            },
            DayPalette::Overcast => Palette {
                sky_zenith: [0.62, 0.65, 0.70],
                sky_horizon: [0.82, 0.83, 0.85],
                grass: [0.33, 0.45, 0.26],
                asphalt: [0.30, 0.31, 0.32],
                sidewalk: [0.60, 0.60, 0.58],
                kerb: [0.76, 0.76, 0.75],
                white_paint: [0.88, 0.88, 0.88],
                yellow_paint: [0.85, 0.72, 0.25],
                sun: sun(0.0, 80.0),
                ambient: 0.68,
                diffuse: 0.3,
            },
        }
    }

    /// The Lambert factor of a surface with unit normal `n`.
    pub fn light(&self, n: DVec3) -> f32 {
        self.ambient + self.diffuse * (n.dot(self.sun).max(0.0) as f32)
    }
}

/// Vehicle body colours (a track picks one by the hash of its id).
pub const VEHICLE_COLOURS: [Rgb; 12] = [
    [0.85, 0.85, 0.86],
    [0.12, 0.12, 0.13],
    [0.55, 0.56, 0.58],
    [0.70, 0.10, 0.10],
    [0.10, 0.22, 0.55],
    [0.92, 0.92, 0.90],
    [0.20, 0.35, 0.22],
    [0.85, 0.65, 0.15],
    [0.35, 0.20, 0.12],
    [0.30, 0.55, 0.75],
    [0.60, 0.10, 0.35],
    [0.40, 0.42, 0.45],
];

/// Building facade colours.
pub const FACADE_COLOURS: [Rgb; 10] = [
    [0.78, 0.70, 0.58],
    [0.62, 0.38, 0.30],
    [0.85, 0.82, 0.75],
    [0.55, 0.58, 0.62],
    [0.72, 0.55, 0.40],
    [0.90, 0.86, 0.70],
    [0.45, 0.45, 0.48],
    [0.68, 0.72, 0.78],
    [0.80, 0.62, 0.55],
    [0.58, 0.50, 0.42],
];

/// Clothing colours of pedestrians and cyclists.
pub const CLOTHES: [Rgb; 8] = [
    [0.15, 0.20, 0.45],
    [0.60, 0.10, 0.10],
    [0.20, 0.20, 0.20],
    [0.85, 0.85, 0.80],
    [0.20, 0.45, 0.25],
    [0.80, 0.60, 0.10],
    [0.45, 0.30, 0.55],
    [0.30, 0.55, 0.70],
];

/// FNV-1a over bytes: stable across platforms and runs (seeds of procedural choices).
pub fn hash_bytes(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

/// A 64-bit mix (splitmix64's finaliser).
#[inline]
pub fn mix64(mut x: u64) -> u64 {
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}
