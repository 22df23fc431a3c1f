//! `voxel`: a RayFronts-style semantic voxel map (being written).
