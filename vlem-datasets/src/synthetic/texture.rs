//! Surface textures and the fixed-light shading of the synthetic scene.
//!
//! A colour is a function of the surface point (in the object's own frame), the surface normal and
//! the material only, never of the viewer: the same point has the same colour in every frame, which
//! is what photometric tracking assumes. Patterns live in the plane of the surface (the two local
//! axes most nearly perpendicular to its normal, so curved surfaces get fixed seams), have soft
//! edges and no detail finer than a few centimetres, so that a pixel (under 1 cm at 4 m) does not
//! alias them; every material also carries value noise at three finer scales (10, 5 and 2.5 cm),
//! so that image gradients exist at every distance.

use nalgebra::Vector3;

use super::rng::{Rng, hash, unit};

/// Cells per side of the periodic noise lattice.
const LATTICE: usize = 128;
/// Lattice values in all.
const CELLS: usize = LATTICE * LATTICE;
const MASK: i64 = LATTICE as i64 - 1;

/// The fixed light of the scene (world frame, unit length): from above, a little to the side.
const LIGHT: [f64; 3] = [0.358_057, 0.501_280, 0.787_726];

/// Samples per side of the precomputed fractal table.
const TABLE: usize = 512;
/// Table samples per noise unit (the finest of its octaves has 4 samples per wavelength).
const TABLE_RES: f64 = 16.0;
/// Units before the table repeats.
const TABLE_PERIOD: usize = TABLE / TABLE_RES as usize;

/// Seeded 2-D value noise (a periodic lattice of random values, smoothly interpolated), and a
/// precomputed three-octave fractal sum of it for the hot path.
#[derive(Clone, Debug)]
pub(crate) struct Noise {
    lattice: Box<[f32; CELLS]>,
    fractal: Box<[f32; TABLE * TABLE]>,
}

impl Noise {
    /// The lattice and fractal table of `seed`.
    pub(crate) fn new(seed: u64) -> Self {
        let mut lattice = Box::new([0.0_f32; CELLS]);
        for (i, value) in lattice.iter_mut().enumerate() {
            *value = unit(hash(&[seed, 0x7e47, i as u64])) as f32;
        }
        let mut noise = Self {
            lattice,
            fractal: Box::new([0.0_f32; TABLE * TABLE]),
        };
        // Octave k has frequency 2^k and lattice period TABLE_PERIOD · 2^k (≤ LATTICE), so the
        // sum repeats every TABLE_PERIOD units; integer shifts keep that and decorrelate octaves.
        let mut fractal = Box::new([0.0_f32; TABLE * TABLE]);
        for (index, value) in fractal.iter_mut().enumerate() {
            let (x, y) = (
                (index % TABLE) as f64 / TABLE_RES,
                (index / TABLE) as f64 / TABLE_RES,
            );
            let mut sum = 0.0;
            for octave in 0..3u32 {
                let scale = f64::from(1u32 << octave);
                let period = (TABLE_PERIOD << octave) as i64;
                let shift = f64::from(37 * octave);
                sum += noise.periodic(x * scale + shift, y * scale + 2.0 * shift, period) / scale;
            }
            *value = (sum / 1.75) as f32;
        }
        noise.fractal = fractal;
        noise
    }

    /// Value noise in `[0, 1]` with unit cell size.
    #[inline]
    pub(crate) fn value(&self, x: f64, y: f64) -> f64 {
        self.periodic(x, y, LATTICE as i64)
    }

    /// Value noise that repeats every `period` cells (a power of two up to [`LATTICE`]).
    #[inline]
    fn periodic(&self, x: f64, y: f64, period: i64) -> f64 {
        let mask = (period - 1) & MASK;
        let (i, fx) = split(x);
        let (j, fy) = split(y);
        let (u, v) = (fade(fx), fade(fy));
        let (x0, x1) = ((i & mask) as usize, ((i + 1) & mask) as usize);
        let (y0, y1) = (
            ((j & mask) as usize) * LATTICE,
            (((j + 1) & mask) as usize) * LATTICE,
        );
        // The mask keeps every index in range, so the compiler drops the bounds checks.
        let at = |index: usize| f64::from(self.lattice[index & (CELLS - 1)]);
        let (a, b) = (at(y0 + x0), at(y0 + x1));
        let (c, d) = (at(y1 + x0), at(y1 + x1));
        let top = a + (b - a) * u;
        let bottom = c + (d - c) * u;
        top + (bottom - top) * v
    }

    /// Three-octave fractal noise in `[0, 1]`, the first octave with cells of `wavelength`
    /// metres (the others half and a quarter of it), read bilinearly from the precomputed table.
    #[inline]
    pub(crate) fn fbm(&self, x: f64, y: f64, wavelength: f64) -> f64 {
        let scale = TABLE_RES / wavelength;
        let (i, fx) = split(x * scale);
        let (j, fy) = split(y * scale);
        const M: i64 = TABLE as i64 - 1;
        let (x0, x1) = ((i & M) as usize, ((i + 1) & M) as usize);
        let (y0, y1) = (((j & M) as usize) * TABLE, (((j + 1) & M) as usize) * TABLE);
        let at = |index: usize| f64::from(self.fractal[index & (TABLE * TABLE - 1)]);
        let (a, b) = (at(y0 + x0), at(y0 + x1));
        let (c, d) = (at(y1 + x0), at(y1 + x1));
        let top = a + (b - a) * fx;
        let bottom = c + (d - c) * fx;
        top + (bottom - top) * fy
    }
}

/// `(n, x - n)` with `n = floor(x)` (or `floor(x) - 1` at exact integers, where the fraction is
/// then 1: the interpolations here are continuous, so both give the same value), for
/// `|x| < 2³⁰`, without a libm call or a branch: adding 1.5 · 2⁵² rounds `x - 0.5` to the nearest
/// integer, whose low 32 bits then sit in the mantissa.
#[inline]
fn split(x: f64) -> (i64, f64) {
    const MAGIC: f64 = 6_755_399_441_055_744.0;
    let shifted = (x - 0.5) + MAGIC;
    // Truncating to the low 32 bits is the point: they hold the rounded value.
    let n = i64::from(shifted.to_bits() as u32 as i32);
    (n, x - (shifted - MAGIC))
}

/// Quintic smoothstep of `t ∈ [0, 1]`.
#[inline]
fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// Smoothstep from `a` to `b`.
#[inline]
fn smoothstep(a: f64, b: f64, x: f64) -> f64 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// A square wave of period 1 with edges `edge` wide (in periods): `-1` on the first half, `+1` on
/// the second, smooth in between.
#[inline]
fn soft_square(x: f64, edge: f64) -> f64 {
    // Triangle wave in [0, 1], 0 at integers: the edges of the square wave sit at 0.25 and 0.75.
    let tri = 2.0 * (x - split(x + 0.5).0 as f64).abs();
    let s = smoothstep(0.5 - edge, 0.5 + edge, tri);
    2.0 * s - 1.0
}

/// Which local axes span the surface whose normal is `n`: the normal's dominant axis is dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Plane {
    /// Normal mostly along z: coordinates (x, y).
    Xy,
    /// Normal mostly along x: coordinates (y, z).
    Yz,
    /// Normal mostly along y: coordinates (x, z).
    Xz,
}

impl Plane {
    #[inline]
    fn of(n: &Vector3<f64>) -> Self {
        let (ax, ay, az) = (n.x.abs(), n.y.abs(), n.z.abs());
        if az >= ax && az >= ay {
            Self::Xy
        } else if ax >= ay {
            Self::Yz
        } else {
            Self::Xz
        }
    }

    #[inline]
    fn coords(self, p: &Vector3<f64>) -> (f64, f64) {
        match self {
            Self::Xy => (p.x, p.y),
            Self::Yz => (p.y, p.z),
            Self::Xz => (p.x, p.z),
        }
    }
}

/// The pattern of a material.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Pattern {
    /// Blotchy paint or plaster: fractal noise with this wavelength (metres).
    Plaster { wavelength: f64 },
    /// Wood grain along the local x axis, `rings` growth rings per metre.
    Wood { rings: f64 },
    /// Floor boards along x: `width` wide and `length` long, with seams and grain.
    Planks { width: f64, length: f64 },
    /// Square tiles of `size` metres with grout lines and a tint per tile.
    Tiles { size: f64 },
    /// A checkerboard of `size` metre squares in the surface's own plane.
    Checker { size: f64 },
    /// Stripes `period` metres apart across the local axis `axis` (0 = x, 1 = y, 2 = z).
    Stripes { period: f64, axis: usize },
    /// Woven fabric: soft checks `weave` metres wide over slow noise.
    Fabric { weave: f64 },
    /// Large soft-edged blobs (posters, pictures).
    Blobs { wavelength: f64 },
}

/// A surface material: two colours mixed by a pattern, with noise detail on top.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Material {
    /// First colour (linear, 0..1).
    pub(crate) a: [f64; 3],
    /// Second colour.
    pub(crate) b: [f64; 3],
    pub(crate) pattern: Pattern,
    /// Offset into the noise field, so that objects made of the same material differ.
    pub(crate) offset: Vector3<f64>,
    /// Relative strength of the multi-scale detail noise (0.18..0.3).
    pub(crate) detail: f64,
}

impl Material {
    /// A material with a random noise offset and detail strength.
    pub(crate) fn new(a: [f64; 3], b: [f64; 3], pattern: Pattern, rng: &mut Rng) -> Self {
        Self {
            a,
            b,
            pattern,
            offset: Vector3::new(
                rng.range(0.0, 500.0),
                rng.range(0.0, 500.0),
                rng.range(0.0, 500.0),
            ),
            detail: rng.range(0.18, 0.3),
        }
    }

    /// The albedo at local point `p` with local normal `n`, each channel in `[0, 1]`.
    pub(crate) fn albedo(&self, noise: &Noise, p: &Vector3<f64>, n: &Vector3<f64>) -> [f64; 3] {
        let plane = Plane::of(n);
        // Patterns are anchored at the piece's origin; only the noise is offset.
        let (s, t) = plane.coords(p);
        let (ns, nt) = plane.coords(&(p + self.offset));
        let (mix, tint) = match self.pattern {
            Pattern::Plaster { wavelength } => {
                let f = noise.fbm(ns, nt, wavelength);
                (smoothstep(0.25, 0.75, f), 1.0)
            }
            Pattern::Wood { rings } => {
                let warp = noise.value(ns * 4.0, nt * 4.0) * 0.08;
                let r = (p.y * p.y + p.z * p.z).sqrt() + warp;
                let ring = 0.5 + 0.5 * (std::f64::consts::TAU * r * rings).sin();
                // Fine grain: stretched along x where x runs in the surface, round on end grain.
                let grain = match plane {
                    Plane::Yz => noise.value(ns * 25.0, nt * 25.0),
                    _ => noise.value(ns * 3.0, nt * 25.0),
                };
                (0.75 * ring * ring + 0.25 * grain, 1.0)
            }
            Pattern::Planks { width, length } => {
                let (row, across) = split(t / width);
                let shift = unit(hash(&[row as u64, 0x91a])) * length;
                let (col, along) = split((s + shift) / length);
                let seam = smoothstep(0.0, 0.06, across.min(1.0 - across))
                    * smoothstep(0.0, 0.012, along.min(1.0 - along));
                let board = unit(hash(&[row as u64, col as u64]));
                let grain = noise.value(ns * 4.0, nt * 30.0 + board * 97.0);
                let mix = (0.55 * board + 0.45 * grain).clamp(0.0, 1.0);
                (mix, 0.55 + 0.45 * seam)
            }
            Pattern::Tiles { size } => {
                let ((iu, fu), (iv, fv)) = (split(s / size), split(t / size));
                let grout = smoothstep(0.0, 0.04, fu.min(1.0 - fu))
                    * smoothstep(0.0, 0.04, fv.min(1.0 - fv));
                let tile = unit(hash(&[iu as u64, iv as u64, 0x711e]));
                let f = noise.value(ns / (size * 0.6), nt / (size * 0.6));
                (0.6 * tile + 0.4 * f, 0.6 + 0.4 * grout)
            }
            Pattern::Checker { size } => {
                let c = soft_square(s / (2.0 * size), 0.06) * soft_square(t / (2.0 * size), 0.06);
                (0.5 + 0.5 * c, 1.0)
            }
            Pattern::Stripes { period, axis } => {
                let x = p[axis.min(2)];
                let stripes = soft_square(x / period, 0.1);
                let f = noise.value(ns * 2.5, nt * 2.5);
                ((0.5 + 0.4 * stripes + 0.2 * (f - 0.5)).clamp(0.0, 1.0), 1.0)
            }
            Pattern::Fabric { weave } => {
                let w = soft_square(s / weave, 0.15) * soft_square(t / weave, 0.15);
                let f = noise.value(ns / 0.3, nt / 0.3);
                ((0.7 * f + 0.15 * w + 0.15).clamp(0.0, 1.0), 1.0)
            }
            Pattern::Blobs { wavelength } => {
                let f = noise.fbm(ns, nt, wavelength);
                (smoothstep(0.42, 0.58, f), 1.0)
            }
        };
        let detail = 1.0 - self.detail + 2.0 * self.detail * noise.fbm(ns, nt, 0.1);
        let k = tint * detail;
        std::array::from_fn(|c| ((self.a[c] + (self.b[c] - self.a[c]) * mix) * k).clamp(0.0, 1.0))
    }
}

/// Lambert-like shading from the fixed world light: `0.65 + 0.35 n·l`, so that surfaces facing
/// away from the light stay visible (no shadows, no view dependence).
#[inline]
pub(crate) fn shade(normal: &Vector3<f64>) -> f64 {
    0.65 + 0.35 * (normal.x * LIGHT[0] + normal.y * LIGHT[1] + normal.z * LIGHT[2])
}

/// The 8-bit colour of `albedo` under `shade`.
#[inline]
pub(crate) fn to_rgb8(albedo: [f64; 3], shade: f64) -> [u8; 3] {
    // Adding 0.5 and truncating rounds these non-negative values without a libm call.
    albedo.map(|c| ((c * shade).clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn light_is_unit_and_noise_is_bounded_and_continuous() {
        let l = Vector3::from(LIGHT);
        assert!((l.norm() - 1.0).abs() < 1e-5);
        let noise = Noise::new(3);
        let mut rng = Rng::new(0, 0);
        for _ in 0..1000 {
            let (x, y) = (rng.range(-500.0, 500.0), rng.range(-50.0, 50.0));
            let f = noise.fbm(x, y, 0.3);
            assert!((0.0..=1.0).contains(&f));
            let g = noise.fbm(x + 1e-6, y, 0.3);
            assert!((f - g).abs() < 1e-3);
            let (v, w) = (noise.value(x, y), noise.value(x, y + 1e-6));
            assert!((0.0..=1.0).contains(&v) && (v - w).abs() < 1e-4);
        }
        assert_ne!(Noise::new(3).lattice[..], Noise::new(4).lattice[..]);
    }

    #[test]
    fn split_is_floor_up_to_integers() {
        for x in [
            -2.5, -2.0, -1.5, -0.5, -0.1, -0.0, 0.0, 0.3, 0.5, 1.0, 1.5, 7.9, -12345.75, 9.9e8,
        ] {
            let (i, f) = split(x);
            assert!((0.0..=1.0).contains(&f), "{x}: {f}");
            assert!((i as f64 + f - x).abs() <= 1e-12 * x.abs().max(1.0), "{x}");
            assert!(
                i as f64 == x.floor() || (x == x.floor() && i as f64 == x - 1.0),
                "{x}"
            );
        }
    }

    #[test]
    fn the_fractal_table_repeats_and_matches_its_octaves() {
        let noise = Noise::new(9);
        let period = TABLE_PERIOD as f64 * 0.1;
        for (x, y) in [(0.013, 0.2), (1.7, -3.1), (-0.05, 0.9)] {
            let a = noise.fbm(x, y, 0.1);
            let b = noise.fbm(x + period, y - period, 0.1);
            assert!((a - b).abs() < 1e-6, "{a} vs {b}");
        }
        // At a table sample, the table holds the octave sum.
        let (x, y) = (3.0 / TABLE_RES, 5.0 / TABLE_RES);
        let direct = (noise.value(x, y)
            + noise.periodic(2.0 * x + 37.0, 2.0 * y + 74.0, 2 * TABLE_PERIOD as i64) / 2.0
            + noise.periodic(4.0 * x + 74.0, 4.0 * y + 148.0, 4 * TABLE_PERIOD as i64) / 4.0)
            / 1.75;
        assert!((noise.fbm(x, y, 1.0) - direct).abs() < 1e-6);
    }

    #[test]
    fn soft_square_takes_both_values() {
        assert!((soft_square(0.0, 0.05) + 1.0).abs() < 1e-12);
        assert!((soft_square(0.5, 0.05) - 1.0).abs() < 1e-12);
        assert!((soft_square(1.0, 0.05) + 1.0).abs() < 1e-12);
        assert!(soft_square(0.25, 0.05).abs() < 1e-12);
    }

    #[test]
    fn every_pattern_varies_over_a_metre() {
        let noise = Noise::new(1);
        let mut rng = Rng::new(1, 1);
        let patterns = [
            Pattern::Plaster { wavelength: 0.3 },
            Pattern::Wood { rings: 25.0 },
            Pattern::Planks {
                width: 0.15,
                length: 1.0,
            },
            Pattern::Tiles { size: 0.3 },
            Pattern::Checker { size: 0.3 },
            Pattern::Stripes {
                period: 0.1,
                axis: 0,
            },
            Pattern::Fabric { weave: 0.05 },
            Pattern::Blobs { wavelength: 0.2 },
        ];
        for pattern in patterns {
            let m = Material::new([0.2; 3], [0.8; 3], pattern, &mut rng);
            let n = Vector3::z();
            let values: Vec<f64> = (0..200)
                .map(|i| {
                    let p = Vector3::new(0.005 * f64::from(i), 0.003 * f64::from(i), 0.0);
                    m.albedo(&noise, &p, &n)[0]
                })
                .collect();
            let (lo, hi) = values
                .iter()
                .fold((1.0_f64, 0.0_f64), |(lo, hi), v| (lo.min(*v), hi.max(*v)));
            assert!(hi - lo > 0.15, "{pattern:?}: {lo}..{hi}");
        }
    }
}
