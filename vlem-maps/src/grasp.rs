//! Grasp poses for a parallel gripper from a point set (being written).
