//! ROS 2 message decoding as the rosbag2 reader does it: CDR payloads of Image, CompressedImage,
//! CameraInfo, TFMessage, Odometry and PoseStamped (the first byte picks the type), then their
//! conversion to vlem's images, camera and poses.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use vlem_datasets::rosbag2::messages::{
    CameraInfo, CompressedDepth, CompressedImage, Image, StampedPose, decode_tf_message,
    inverse_depth_to_metres,
};

fuzz_target!(|input: &[u8]| {
    let Some((&kind, data)) = input.split_first() else {
        return;
    };
    match kind % 6 {
        0 => {
            if let Ok(image) = Image::decode(data) {
                if let Ok(colour) = image.to_colour() {
                    assert_eq!(colour.as_raw().len(), image.width as usize * image.height as usize * 3);
                }
                if let Ok(depth) = image.to_depth(1000.0) {
                    assert!(depth.as_raw().iter().all(|d| d.is_finite() && *d >= 0.0));
                }
            }
        }
        1 => {
            if let Ok(message) = CompressedImage::decode(data) {
                match message.depth() {
                    Ok(CompressedDepth::Raw16(png)) => {
                        let _ = vlem_datasets::depth_from_bytes(png, 1000.0, Path::new("d.png"));
                    }
                    Ok(CompressedDepth::InverseDepth { png, quant_a, quant_b }) => {
                        if let Ok(raw) = vlem_datasets::depth_from_bytes(png, 1.0, Path::new("d.png")) {
                            for &v in raw.as_raw() {
                                let d = inverse_depth_to_metres(v as u16, quant_a, quant_b);
                                assert!(d.is_finite() && d >= 0.0);
                            }
                        }
                    }
                    Err(_) => {}
                }
                let _ = vlem_datasets::colour_from_bytes(message.data, Path::new("c.jpg"));
            }
        }
        2 => {
            if let Ok(info) = CameraInfo::decode(data)
                && let Ok(k) = info.intrinsics()
            {
                assert!(k.validate().is_ok());
            }
        }
        3 => {
            for t in decode_tf_message(data).into_iter().flatten() {
                if let Ok(pose) = t.transform {
                    assert!(pose.to_homogeneous().iter().all(|v| v.is_finite()));
                }
            }
        }
        kind => {
            let decoded = if kind == 4 {
                StampedPose::decode_odometry(data)
            } else {
                StampedPose::decode_pose_stamped(data)
            };
            if let Ok(StampedPose { pose: Ok(pose), .. }) = decoded {
                assert!((pose.rotation.quaternion().norm() - 1.0).abs() < 1e-9);
            }
        }
    }
});
