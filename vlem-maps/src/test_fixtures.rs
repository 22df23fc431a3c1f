//! The frames and embeddings the maps' unit tests observe, in one place (each map's tests had
//! their own copy): a small fronto-parallel plane and one embedding for all of it.

use vlem_core::{
    DepthImage, EmbeddingMap, Frame, IntegrationStats, Intrinsics, Observation, PixelEmbeddings,
    Pose, RgbImage,
};

/// Embedding dimension of the fixtures.
pub const DIM: usize = 4;
/// Frame width, pixels.
pub const W: u32 = 16;
/// Frame height, pixels.
pub const H: u32 = 12;

/// A 16x12 fronto-parallel frame with one depth per pixel; at 1 m a pixel covers 5 cm.
pub fn plane_with(depth: Vec<f32>) -> Frame {
    let k = Intrinsics::new(W, H, 20.0, 20.0, 7.5, 5.5).unwrap();
    Frame::new(
        0,
        0.0,
        RgbImage::filled(W, H, [200, 100, 0]),
        DepthImage::new(W, H, depth).unwrap(),
        k,
        None,
    )
    .unwrap()
}

/// [`plane_with`] at one depth.
pub fn plane(depth: f32) -> Frame {
    plane_with(vec![depth; (W * H) as usize])
}

/// Embedding `e` for every pixel (one segment).
pub fn uniform(e: [f32; DIM]) -> PixelEmbeddings {
    PixelEmbeddings::from_regions(W, H, DIM, vec![0; (W * H) as usize], e.to_vec()).unwrap()
}

/// Integrates frame `f` seen from `pose` with embeddings `e`.
pub fn integrate<M: EmbeddingMap + ?Sized>(
    m: &mut M,
    f: &Frame,
    pose: &Pose,
    e: &PixelEmbeddings,
) -> IntegrationStats {
    m.integrate(&Observation {
        frame: f,
        pose,
        embeddings: Some(e),
    })
    .unwrap()
}

/// The identity rotation, `x` metres along the x axis.
pub fn translated(x: f64) -> Pose {
    Pose::from_parts(
        nalgebra::Translation3::new(x, 0.0, 0.0),
        nalgebra::UnitQuaternion::identity(),
    )
}
