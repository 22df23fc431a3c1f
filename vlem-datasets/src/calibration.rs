//! Camera intrinsics files and the documented defaults of layouts that ship none.

use std::path::Path;

use serde::Deserialize;
use vlem_core::Intrinsics;

use crate::error::{DatasetError, Result};
use crate::text::read_text;

/// The intrinsics TUM RGB-D publishes as the "ROS default" for its 640x480 Kinect frames
/// (fx = fy = 525, cx = 319.5, cy = 239.5). TUM ships no calibration file, and the folder does not
/// say which of the three Kinects (freiburg1/2/3) recorded it, so this is the one value valid for
/// all of them; pass the sequence's own calibration as an Open3D JSON in `[dataset] intrinsics`
/// for better geometry.
pub const TUM_DEFAULT_INTRINSICS: Intrinsics = Intrinsics {
    width: 640,
    height: 480,
    fx: 525.0,
    fy: 525.0,
    cx: 319.5,
    cy: 239.5,
};

/// The camera of Replica as rendered and packaged by NICE-SLAM (its `configs/Replica/replica.yaml`):
/// 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5. Used when `[dataset] intrinsics` is not set.
pub const REPLICA_DEFAULT_INTRINSICS: Intrinsics = Intrinsics {
    width: 1200,
    height: 680,
    fx: 600.0,
    fy: 600.0,
    cx: 599.5,
    cy: 339.5,
};

/// Open3D's `PinholeCameraIntrinsic` JSON.
#[derive(Deserialize)]
struct Open3dIntrinsics {
    width: u32,
    height: u32,
    /// Column-major 3x3 matrix: fx at 0, fy at 4, cx at 6, cy at 7.
    intrinsic_matrix: Vec<f64>,
}

/// Reads an Open3D `PinholeCameraIntrinsic` JSON file (`width`, `height` and the column-major
/// 3x3 `intrinsic_matrix`), as ICL-NUIM and Redwood folders carry it.
///
/// # Errors
/// [`DatasetError::MissingFile`] / [`DatasetError::Io`] when the file cannot be read, and those of
/// [`open3d_intrinsics_from_str`].
pub fn read_open3d_intrinsics(path: &Path) -> Result<Intrinsics> {
    open3d_intrinsics_from_str(&read_text(path)?, path)
}

/// Parses the text of an Open3D `PinholeCameraIntrinsic` JSON file (see
/// [`read_open3d_intrinsics`]); `origin` is the file it came from, as errors name it.
///
/// # Errors
/// [`DatasetError::Parse`] for invalid JSON or a matrix without 9 numbers, and
/// [`DatasetError::Core`] for intrinsics that fail validation.
pub fn open3d_intrinsics_from_str(text: &str, origin: &Path) -> Result<Intrinsics> {
    let json: Open3dIntrinsics = serde_json::from_str(text)
        .map_err(|e| DatasetError::parse(origin, e.line(), e.to_string()))?;
    let m = &json.intrinsic_matrix;
    if m.len() != 9 {
        return Err(DatasetError::parse(
            origin,
            1,
            format!(
                "`intrinsic_matrix` must hold 9 numbers (a column-major 3x3 matrix), found {}",
                m.len()
            ),
        ));
    }
    validated(
        Intrinsics::new(json.width, json.height, m[0], m[4], m[6], m[7]),
        origin,
    )
}

/// Attaches the file to an intrinsics validation error.
pub(crate) fn validated(
    intrinsics: vlem_core::Result<Intrinsics>,
    path: &Path,
) -> Result<Intrinsics> {
    intrinsics.map_err(|source| DatasetError::Core {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid() {
        TUM_DEFAULT_INTRINSICS.validate().unwrap();
        REPLICA_DEFAULT_INTRINSICS.validate().unwrap();
    }

    #[test]
    fn open3d_json_is_column_major_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("k.json");
        std::fs::write(
            &path,
            r#"{"width": 320, "height": 240, "intrinsic_matrix": [300, 0, 0, 0, 310, 0, 160.5, 120.5, 1]}"#,
        )
        .unwrap();
        let k = read_open3d_intrinsics(&path).unwrap();
        assert_eq!((k.width, k.height), (320, 240));
        assert_eq!((k.fx, k.fy, k.cx, k.cy), (300.0, 310.0, 160.5, 120.5));

        std::fs::write(
            &path,
            r#"{"width": 320, "height": 240, "intrinsic_matrix": [1, 2]}"#,
        )
        .unwrap();
        let err = read_open3d_intrinsics(&path).unwrap_err().to_string();
        assert!(
            err.contains("k.json:1: `intrinsic_matrix` must hold 9"),
            "{err}"
        );

        std::fs::write(&path, "{\n\"width\": 320,\n}").unwrap();
        let err = read_open3d_intrinsics(&path).unwrap_err().to_string();
        assert!(err.contains("k.json:3:"), "{err}");

        std::fs::write(
            &path,
            r#"{"width": 320, "height": 240, "intrinsic_matrix": [0, 0, 0, 0, 310, 0, 160.5, 120.5, 1]}"#,
        )
        .unwrap();
        let err = read_open3d_intrinsics(&path).unwrap_err().to_string();
        assert!(err.contains("k.json: invalid intrinsics"), "{err}");
    }
}
