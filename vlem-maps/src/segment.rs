//! `segment`: an Open-Fusion-style map of 3D segments (being written).
