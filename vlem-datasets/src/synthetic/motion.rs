//! The camera path of the synthetic scene: a slow, wobbling orbit around the middle of the room,
//! looking outwards at the walls and furniture, like a handheld sensor at 30 Hz.
//!
//! The path is a closed-form function of the frame index (never integrated), so every pose is
//! exact and independent of how many frames are rendered. Per frame the camera moves about 1 cm
//! (at most 1.8 cm) and turns about 1° (at most 1.7°); it orbits once in 380–440 frames, pitching
//! between about 36° down and 9° up (mostly 30° to 2° down, every 120–150 frames).

use std::f64::consts::TAU;

use nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use vlem_core::Pose;

use super::rng::Rng;

/// Amplitude of the orbit centre's drift along x and y (metres).
const DRIFT: f64 = 0.2;

/// A sinusoid `amplitude · sin(2π i / period + phase)`.
#[derive(Clone, Copy, Debug)]
struct Wave {
    amplitude: f64,
    period: f64,
    phase: f64,
}

impl Wave {
    fn new(rng: &mut Rng, amplitude: f64, period: (f64, f64)) -> Self {
        Self {
            amplitude,
            period: rng.range(period.0, period.1),
            phase: rng.range(0.0, TAU),
        }
    }

    fn at(&self, i: f64) -> f64 {
        self.amplitude * (TAU * i / self.period + self.phase).sin()
    }
}

/// The seeded camera path.
#[derive(Clone, Debug)]
pub(crate) struct Motion {
    radius: f64,
    radius_wave: Wave,
    height: f64,
    height_wave: Wave,
    /// Orbit angle at frame 0 and its change per frame (signed: the direction is seeded).
    orbit_phase: f64,
    orbit_rate: f64,
    yaw_wave: Wave,
    /// A slow sideways drift of the orbit centre, so that the camera also translates when the
    /// orbit itself is small.
    drift: [Wave; 2],
    pitch: f64,
    pitch_wave: Wave,
    /// A slower pitch swing that now and then lifts the view to the ceiling.
    pitch_swell: Wave,
    roll_wave: Wave,
    /// Maps camera axes (x right, y down, z forward) to world axes for a camera looking along +x.
    base: UnitQuaternion<f64>,
}

impl Motion {
    /// The path of `seed` in a room of `size` (x extent, y extent, height) centred on the z axis
    /// with its floor at z = 0.
    pub(crate) fn new(seed: u64, size: [f64; 3]) -> Self {
        let mut rng = Rng::new(seed, 0x6d6f_7469_6f6e);
        let radius = (0.1 * size[0].min(size[1])).clamp(0.3, 0.8);
        let height = (0.5 * size[2]).min(1.4);
        let direction = if rng.chance(0.5) { 1.0 } else { -1.0 };
        let base = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
            Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0),
        ));
        Self {
            radius,
            radius_wave: Wave::new(&mut rng, 0.15 * radius, (150.0, 190.0)),
            height,
            height_wave: Wave::new(&mut rng, 0.1, (200.0, 260.0)),
            orbit_phase: rng.range(0.0, TAU),
            orbit_rate: direction * TAU / rng.range(380.0, 440.0),
            yaw_wave: Wave::new(&mut rng, 0.25, (250.0, 320.0)),
            drift: [
                Wave::new(&mut rng, DRIFT, (170.0, 230.0)),
                Wave::new(&mut rng, DRIFT, (170.0, 230.0)),
            ],
            pitch: -0.25,
            pitch_wave: Wave::new(&mut rng, 0.28, (120.0, 150.0)),
            pitch_swell: Wave::new(&mut rng, 0.12, (330.0, 400.0)),
            roll_wave: Wave::new(&mut rng, 0.04, (230.0, 290.0)),
            base,
        }
    }

    /// The farthest the camera gets from the room's vertical axis.
    pub(crate) fn max_radius(&self) -> f64 {
        self.radius + self.radius_wave.amplitude + DRIFT * std::f64::consts::SQRT_2
    }

    /// Frames of one full orbit (the path then has looked in every direction).
    pub(crate) fn orbit_frames(&self) -> usize {
        (TAU / self.orbit_rate.abs()).ceil() as usize
    }

    /// The camera-to-world pose of frame `index`.
    pub(crate) fn pose(&self, index: usize) -> Pose {
        let i = index as f64;
        let orbit = self.orbit_phase + self.orbit_rate * i;
        let r = self.radius + self.radius_wave.at(i);
        let position = Vector3::new(
            r * orbit.cos() + self.drift[0].at(i),
            r * orbit.sin() + self.drift[1].at(i),
            self.height + self.height_wave.at(i),
        );
        let yaw = orbit + self.yaw_wave.at(i);
        let pitch = self.pitch + self.pitch_wave.at(i) + self.pitch_swell.at(i);
        let roll = self.roll_wave.at(i);
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw)
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -pitch)
            * self.base
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll);
        Pose::from_parts(Translation3::from(position), rotation)
    }
}

/// A camera-to-world pose at `position` looking along `forward`, with no roll (world z is up, so
/// image rows stay level); `forward` must not be vertical.
pub fn look_along(position: Vector3<f64>, forward: Vector3<f64>) -> Pose {
    let z = forward.normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Pose::from_parts(
        Translation3::from(position),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn path_is_smooth_and_looks_outwards_and_slightly_down() {
        let m = Motion::new(0, [5.5, 4.5, 2.7]);
        let mut max_step: f64 = 0.0;
        let mut max_turn: f64 = 0.0;
        for i in 0..600 {
            let (a, b) = (m.pose(i), m.pose(i + 1));
            max_step = max_step.max((b.translation.vector - a.translation.vector).norm());
            max_turn = max_turn.max(a.rotation.angle_to(&b.rotation));
            let forward = a.rotation * Vector3::z();
            assert!(forward.z < 0.2 && forward.z > -0.62, "{forward}");
            // Outwards: within the yaw sway (0.25 rad) plus what the drift adds.
            let out = a.translation.vector.xy().normalize();
            assert!(forward.xy().normalize().dot(&out) > 0.5);
            // Camera y (down) points down in the world.
            assert!((a.rotation * Vector3::y()).z < -0.75);
        }
        assert!(max_step > 0.01 && max_step < 0.02, "{max_step}");
        assert!(
            max_turn.to_degrees() > 0.7 && max_turn.to_degrees() < 2.0,
            "{max_turn}"
        );
    }

    #[test]
    fn look_along_is_a_camera_pose() {
        let p = look_along(Vector3::new(1.0, 2.0, 1.5), Vector3::new(1.0, 0.0, 0.0));
        assert!((p.rotation * Vector3::z() - Vector3::x()).norm() < 1e-12);
        assert!((p.rotation * Vector3::x() + Vector3::y()).norm() < 1e-12);
        assert!((p.rotation * Vector3::y() + Vector3::z()).norm() < 1e-12);
    }
}
