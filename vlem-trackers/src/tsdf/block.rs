//! Voxel blocks, the unit of storage and of parallel work in the TSDF map.
//!
//! A block holds `8 x 8 x 8` voxels. The voxel with global integer index `g` has its centre at
//! `g * voxel_size` in world coordinates and lives in block `g >> 3` at local index `g & 7`.

/// Voxels per block edge.
pub(crate) const BLOCK_RES: usize = 8;
/// `log2(BLOCK_RES)`: global voxel index `>> BLOCK_SHIFT` is the block coordinate.
pub(crate) const BLOCK_SHIFT: i32 = 3;
/// `BLOCK_RES - 1`: global voxel index `& BLOCK_MASK` is the index inside the block.
pub(crate) const BLOCK_MASK: i32 = 7;
/// Voxels per block.
pub(crate) const BLOCK_VOXELS: usize = BLOCK_RES * BLOCK_RES * BLOCK_RES;
/// Fixed-point scale of the stored colour: a channel value `c` in `[0, 255]` is stored as
/// `c * COLOUR_SCALE`, so running averages keep sub-level precision.
pub(crate) const COLOUR_SCALE: f32 = 256.0;

/// The stored TSDF of a voxel nobody has observed: outside `[-1, 1]`, so the ray cast tells
/// unobserved voxels from the TSDF alone.
pub(crate) const UNOBSERVED: f32 = 2.0;

/// The TSDF the ray cast reads in space no block covers (see [`UNALLOCATED_BLOCK`]); also
/// counts as unobserved.
pub(crate) const UNALLOCATED: f32 = 4.0;

/// Scale of the 8-bit TSDF copy the ray cast marches on: `q = round(tsdf * MARCH_SCALE)`.
pub(crate) const MARCH_SCALE: f32 = 126.0;
/// The 8-bit TSDF of an unobserved voxel.
pub(crate) const MARCH_UNOBSERVED: i8 = i8::MIN;
/// The 8-bit TSDF everywhere in [`UNALLOCATED_BLOCK`].
pub(crate) const MARCH_UNALLOCATED: i8 = i8::MAX;

/// The 8-bit TSDF of a stored value (observed: in `[-1, 1]`).
#[inline]
pub(crate) fn march_value(tsdf: f32) -> i8 {
    let q = tsdf.clamp(-1.0, 1.0) * MARCH_SCALE;
    // Rounded half away from zero (the cast truncates towards zero); in [-126, 126].
    (q + 0.5_f32.copysign(q)) as i8
}

/// Index of local voxel `(x, y, z)` in [`Block::march`]: bricks of `4³` voxels (64 bytes, one
/// cache line each), so a ray's neighbouring samples share lines in every direction.
#[inline]
pub(crate) fn brick_index(x: usize, y: usize, z: usize) -> usize {
    let brick = (x >> 2) | (y >> 2) << 1 | (z >> 2) << 2;
    let inside = (x & 3) | (y & 3) << 2 | (z & 3) << 4;
    brick << 6 | inside
}

/// Whether a stored TSDF value belongs to an unobserved voxel.
#[inline]
pub(crate) fn unobserved(tsdf: f32) -> bool {
    tsdf > 1.5
}

/// One voxel's values, copied out of a [`Block`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Voxel {
    /// Signed distance divided by the truncation distance, in `[-1, 1]`; positive in front of
    /// the surface (free space). [`UNOBSERVED`] while `weight` is 0.
    pub tsdf: f32,
    /// Number of observations fused (capped); 0 = never observed.
    pub weight: u16,
    /// Running average colour, RGB, in units of `1 / COLOUR_SCALE` of an 8-bit level.
    pub rgb: [u16; 3],
}

impl Voxel {
    /// A voxel nobody has observed.
    pub const EMPTY: Self = Self {
        tsdf: UNOBSERVED,
        weight: 0,
        rgb: [0; 3],
    };

    /// The colour as floating-point 8-bit levels.
    #[inline]
    pub fn colour(&self) -> [f32; 3] {
        let s = 1.0 / COLOUR_SCALE;
        [
            f32::from(self.rgb[0]) * s,
            f32::from(self.rgb[1]) * s,
            f32::from(self.rgb[2]) * s,
        ]
    }
}

/// `8^3` voxels at block coordinate `coord`, one array per field, each indexed by
/// [`voxel_index`] (x fastest), plus an 8-bit copy of the TSDF in bricks for marching rays.
/// 6.5 KiB.
#[derive(Clone)]
pub(crate) struct Block {
    /// Block coordinate: the block holds global voxel indices `coord * 8 .. coord * 8 + 7`.
    pub coord: [i32; 3],
    /// Whether a voxel was ever fused to within a fifth of the truncation distance of a
    /// surface (`|tsdf| < 0.2`); ray casts start marching only near such blocks.
    pub near_surface: bool,
    /// The TSDF in 8 bits (see [`march_value`]; [`MARCH_UNOBSERVED`] while unobserved),
    /// indexed by [`brick_index`]: all a marching ray reads.
    pub march: [i8; BLOCK_VOXELS],
    /// See [`Voxel::tsdf`].
    pub tsdf: [f32; BLOCK_VOXELS],
    /// See [`Voxel::weight`].
    pub weight: [u16; BLOCK_VOXELS],
    /// See [`Voxel::rgb`]: one array per channel.
    pub rgb: [[u16; BLOCK_VOXELS]; 3],
}

impl Block {
    /// A block of unobserved voxels, on the heap.
    pub fn boxed(coord: [i32; 3]) -> Box<Self> {
        Box::new(Self {
            coord,
            near_surface: false,
            march: [MARCH_UNOBSERVED; BLOCK_VOXELS],
            tsdf: [UNOBSERVED; BLOCK_VOXELS],
            weight: [0; BLOCK_VOXELS],
            rgb: [[0; BLOCK_VOXELS]; 3],
        })
    }

    /// The voxel at index `i` (see [`voxel_index`]; taken modulo 512).
    #[inline]
    pub fn voxel(&self, i: usize) -> Voxel {
        let i = i % BLOCK_VOXELS;
        Voxel {
            tsdf: self.tsdf[i],
            weight: self.weight[i],
            rgb: [0, 1, 2].map(|channel| self.rgb[channel][i]),
        }
    }
}

/// Stands in for every block that is not allocated, so lookups need no `Option`.
pub(crate) static UNALLOCATED_BLOCK: Block = Block {
    coord: [i32::MIN; 3],
    near_surface: false,
    march: [MARCH_UNALLOCATED; BLOCK_VOXELS],
    tsdf: [UNALLOCATED; BLOCK_VOXELS],
    weight: [0; BLOCK_VOXELS],
    rgb: [[0; BLOCK_VOXELS]; 3],
};

/// Index of local voxel `(x, y, z)` (each in `0..8`) in the arrays of a [`Block`].
#[inline]
pub(crate) fn voxel_index(x: usize, y: usize, z: usize) -> usize {
    x | (y << 3) | (z << 6)
}

/// Index inside its block of the voxel with global index `g`.
#[inline]
pub(crate) fn local_index(g: [i32; 3]) -> usize {
    // Masked to 0..8, so the casts are exact.
    voxel_index(
        (g[0] & BLOCK_MASK) as usize,
        (g[1] & BLOCK_MASK) as usize,
        (g[2] & BLOCK_MASK) as usize,
    )
}

/// Block coordinate of the voxel with global index `g`.
#[inline]
pub(crate) fn block_of(g: [i32; 3]) -> [i32; 3] {
    [
        g[0] >> BLOCK_SHIFT,
        g[1] >> BLOCK_SHIFT,
        g[2] >> BLOCK_SHIFT,
    ]
}
