//! Every failure names the file to fix.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "tests")]

mod common;

use vlem_core::config::DatasetConfig;
use vlem_datasets::{DatasetError, IclReader, detect_kind};

fn icl_error(dir: &std::path::Path) -> String {
    IclReader::open(dir, &DatasetConfig::default())
        .unwrap_err()
        .to_string()
}

#[test]
fn missing_depth_folder() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 2, false);
    std::fs::remove_dir_all(tmp.path().join("depth")).unwrap();
    let err = icl_error(tmp.path());
    let depth = tmp.path().join("depth");
    assert!(
        err.starts_with(&format!("{}: not found", depth.display())),
        "{err}"
    );
    assert!(
        err.contains("needs depth/ holding 16-bit .png frames"),
        "{err}"
    );
}

#[test]
fn missing_intrinsics_lists_what_was_looked_for() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 2, false);
    std::fs::remove_file(tmp.path().join("intrinsics.json")).unwrap();
    let err = icl_error(tmp.path());
    assert!(err.contains("intrinsics.json: not found"), "{err}");
    assert!(
        err.contains("intrinsics.json and camera_intrinsic.json"),
        "{err}"
    );
    assert!(err.contains("[dataset] intrinsics"), "{err}");

    let config = DatasetConfig::default()
        .with_param("intrinsics", "nowhere.json")
        .unwrap();
    let err = IclReader::open(tmp.path(), &config)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("nowhere.json: not found (set by [dataset] intrinsics)"),
        "{err}"
    );
}

#[test]
fn colour_and_depth_of_different_sizes() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 2, false);
    let colour = tmp.path().join("color/00001.png");
    common::write_rgb(&colour, 5, 3, [0, 0, 0]);
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    assert!(reader.load(0).is_ok());
    let err = reader.load(1).unwrap_err();
    assert!(matches!(err, DatasetError::SizeMismatch { .. }), "{err:?}");
    let depth = tmp.path().join("depth/00001.png");
    assert_eq!(
        err.to_string(),
        format!(
            "colour image {} is 5x3 but depth image {} is 4x3; the two must be registered at the same resolution",
            colour.display(),
            depth.display()
        )
    );
}

#[test]
fn garbage_image_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 1, false);
    let colour = tmp.path().join("color/00000.png");
    std::fs::write(&colour, b"\x89PNG\r\n\x1a\nthis is not really a png").unwrap();
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    let err = reader.load(0).unwrap_err().to_string();
    assert!(
        err.starts_with(&format!("{}: cannot decode image", colour.display())),
        "{err}"
    );
}

#[test]
fn eight_bit_depth_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 1, false);
    let depth = tmp.path().join("depth/00000.png");
    image::GrayImage::from_pixel(4, 3, image::Luma([100]))
        .save(&depth)
        .unwrap();
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    let err = reader.load(0).unwrap_err().to_string();
    assert_eq!(
        err,
        format!(
            "{}: depth must be a 16-bit single-channel image, this one is L8 (8 bits per pixel)",
            depth.display()
        )
    );
}

#[test]
fn non_finite_pose_in_log() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 2, false);
    let log = tmp.path().join("trajectory.log");
    let mut bad = common::translation(0.0, 0.0, 0.0);
    bad[1][3] = f64::NAN;
    common::write_log(&log, &[common::translation(0.0, 0.0, 0.0), bad]);
    let err = icl_error(tmp.path());
    assert_eq!(
        err,
        format!("{}: the pose of frame 1 is not finite", log.display())
    );
}

#[test]
fn too_few_poses() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 3, false);
    let log = tmp.path().join("trajectory.log");
    common::write_log(&log, &[common::translation(0.0, 0.0, 0.0); 2]);
    let err = icl_error(tmp.path());
    assert_eq!(
        err,
        format!("{}: holds 2 poses but 3 frames need one", log.display())
    );
    // Using only the first two frames is fine.
    let config = DatasetConfig {
        max_frames: Some(2),
        ..DatasetConfig::default()
    };
    assert!(IclReader::open(tmp.path(), &config).is_ok());
}

#[test]
fn truncated_log_names_the_line() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 1, false);
    let log = tmp.path().join("trajectory.log");
    std::fs::write(&log, "0 0 1\n1 0 0 0\n0 1 0 0\n").unwrap();
    let err = icl_error(tmp.path());
    assert_eq!(
        err,
        format!(
            "{}:1: frame 0: the file ends after 2 of the 4 matrix rows",
            log.display()
        )
    );
    std::fs::write(&log, "0 0 1\n1 0 0 0\n0 1 zero 0\n0 0 1 0\n0 0 0 1\n").unwrap();
    let err = icl_error(tmp.path());
    assert_eq!(err, format!("{}:3: `zero` is not a number", log.display()));
}

#[test]
fn empty_folders() {
    let tmp = tempfile::tempdir().unwrap();
    let err = common::open_error(&DatasetConfig::default(), tmp.path());
    assert_eq!(
        err,
        format!("{}: the dataset holds no frames", tmp.path().display())
    );

    // An ICL layout whose folders hold no frames.
    std::fs::create_dir(tmp.path().join("color")).unwrap();
    std::fs::create_dir(tmp.path().join("depth")).unwrap();
    common::write_intrinsics(
        &tmp.path().join("intrinsics.json"),
        4,
        3,
        5.0,
        5.0,
        1.5,
        1.0,
    );
    let err = common::open_error(&DatasetConfig::default(), tmp.path());
    assert_eq!(
        err,
        format!("{}: the dataset holds no frames", tmp.path().display())
    );
}

#[test]
fn unknown_layout_lists_what_was_looked_for() {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("notes.txt"), "hello").unwrap();
    std::fs::create_dir(tmp.path().join("pictures")).unwrap();
    let err = detect_kind(tmp.path()).unwrap_err();
    assert!(matches!(err, DatasetError::UnknownLayout { .. }), "{err:?}");
    let err = err.to_string();
    assert!(
        err.starts_with(&format!("{}: unknown dataset layout", tmp.path().display())),
        "{err}"
    );
    for looked_for in [
        "rgb.txt and depth.txt",
        "results/",
        "intrinsic/",
        "color/ or image/",
        "rgbd.match",
    ] {
        assert!(err.contains(looked_for), "{err}");
    }
    assert!(err.ends_with("found notes.txt, pictures/"), "{err}");

    let err = detect_kind(&tmp.path().join("absent"))
        .unwrap_err()
        .to_string();
    assert!(
        err.ends_with("absent: not found (the dataset folder does not exist)"),
        "{err}"
    );
}

#[test]
fn colour_and_depth_counts_differ() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 3, false);
    std::fs::remove_file(tmp.path().join("depth/00001.png")).unwrap();
    let err = icl_error(tmp.path());
    assert!(err.contains("holds 3 colour images but"), "{err}");
    assert!(
        err.contains("holds 2 depth images; add an rgbd.match"),
        "{err}"
    );
}

#[test]
fn bad_config_values() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 1, false);
    let config = DatasetConfig {
        depth_scale: Some(0.0),
        kind: "icl".into(),
        ..DatasetConfig::default()
    };
    let err = common::open_error(&config, tmp.path());
    assert!(
        err.ends_with(
            "[dataset] depth_scale must be a positive number of raw units per metre, got 0"
        ),
        "{err}"
    );
}

#[test]
fn match_file_naming_a_missing_image() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 1, false);
    std::fs::write(
        tmp.path().join("rgbd.match"),
        "depth/00000.png color/00007.png\n",
    )
    .unwrap();
    let err = icl_error(tmp.path());
    assert!(
        err.contains("color/00007.png: not found (listed in"),
        "{err}"
    );
    assert!(err.ends_with("rgbd.match line 1)"), "{err}");
}

#[test]
fn a_depth_image_of_another_size_is_refused_from_its_header_before_decoding() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 1, false);
    let depth = tmp.path().join("depth/00000.png");
    let huge = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(4000, 4000);
    huge.save(&depth).unwrap();
    // Keep the header, drop most of the pixel data: decoding would fail, reading the header not.
    let bytes = std::fs::read(&depth).unwrap();
    std::fs::write(&depth, &bytes[..200]).unwrap();
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    let err = reader.load(0).unwrap_err().to_string();
    // The colour image still matches the camera, so the pair is what is inconsistent.
    assert!(
        err.ends_with(&format!(
            "but depth image {} is 4000x4000; the two must be registered at the same resolution",
            depth.display()
        )),
        "{err}"
    );
    // Colour of the same (wrong) size: then the camera is what disagrees.
    let colour = tmp.path().join("color/00000.png");
    image::RgbImage::new(4000, 4000).save(&colour).unwrap();
    let err = reader.load(0).unwrap_err().to_string();
    assert!(
        err.starts_with(&format!(
            "{} is 4000x4000 but the intrinsics",
            depth.display()
        )) && err.ends_with("are for 4x3"),
        "{err}"
    );
}

/// A bag is recognised in every build; without the `rosbag2` feature opening it says how to build
/// the reader, and `[dataset.rosbag2]` with another kind is a mistake, not ignored.
#[test]
fn bags_are_detected_and_a_build_without_the_reader_says_so() {
    let bag = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/rosbag2/raw-mcap");
    assert_eq!(detect_kind(&bag).unwrap(), "rosbag2");
    let config = DatasetConfig::named("rosbag2");
    let opened = vlem_datasets::open(&config, &bag);
    if cfg!(feature = "rosbag2") {
        // The default topics are not in this bag: the error lists the ones that are.
        let err = opened.err().unwrap().to_string();
        assert!(
            err.contains("/raw/rgb8 (sensor_msgs/msg/Image, 3 messages)"),
            "{err}"
        );
    } else {
        let err = opened.err().unwrap().to_string();
        assert!(
            err.contains("cargo build --release --features rosbag2"),
            "{err}"
        );
    }
    let config = DatasetConfig::named("icl")
        .with_param("rosbag2", vlem_datasets::Rosbag2Config::default())
        .unwrap();
    let err = vlem_datasets::open(&config, &bag)
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.starts_with("[dataset] kind = \"icl\": unknown field `rosbag2`"),
        "{err}"
    );
}

/// Removes frame `k`'s colour and depth images from an ICL folder written by `write_icl`.
fn delete_frame(dir: &std::path::Path, k: usize) {
    std::fs::remove_file(dir.join(format!("color/{k:05}.png"))).unwrap();
    std::fs::remove_file(dir.join(format!("depth/{k:05}.png"))).unwrap();
}

#[test]
fn a_deleted_frame_shifts_no_pose_and_is_a_warning() {
    use vlem_core::FrameSource;
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 6, true);
    delete_frame(tmp.path(), 2);
    let mut reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    assert_eq!(reader.len(), 5);
    // Frame k's pose is at x = k: the frames after the gap keep theirs.
    let xs: Vec<f64> = (0..5)
        .map(|i| reader.load(i).unwrap().pose.unwrap().translation.vector.x)
        .collect();
    assert_eq!(xs, [0.0, 1.0, 3.0, 4.0, 5.0]);
    let warnings = reader.warnings();
    assert_eq!(warnings.len(), 1, "{warnings:?}");
    assert!(
        warnings[0].contains("frame 2 missing") && warnings[0].contains("by frame number"),
        "{warnings:?}"
    );
    assert!(reader.frame(2).is_ok());
    // Without a trajectory, the gap is still said.
    std::fs::remove_file(tmp.path().join("trajectory.log")).unwrap();
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    assert!(reader.warnings()[0].contains("mapped as neighbours"));
}

#[test]
fn a_gap_whose_frames_the_trajectory_does_not_number_is_an_error_naming_the_file() {
    // Files numbered from 1, the .log's frame ids from 0: fine in order, but not with a gap.
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 1, 5, true);
    assert!(IclReader::open(tmp.path(), &DatasetConfig::default()).is_ok());
    delete_frame(tmp.path(), 3);
    let err = icl_error(tmp.path());
    let depth = tmp.path().join("depth/00005.png");
    assert!(
        err.starts_with(&format!(
            "{}: frame 5 has no pose in {}; frames are missing from the folder (frame 3)",
            depth.display(),
            tmp.path().join("trajectory.log").display()
        )),
        "{err}"
    );
}

#[test]
fn colour_and_depth_of_different_frames_are_not_paired() {
    // One colour and another frame's depth image gone: equal counts, shifted pairs.
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 6, false);
    std::fs::remove_file(tmp.path().join("color/00003.png")).unwrap();
    std::fs::remove_file(tmp.path().join("depth/00004.png")).unwrap();
    let err = icl_error(tmp.path());
    assert!(
        err.starts_with(&format!(
            "{} is paired with {} by their sorted order, but their frame numbers differ",
            tmp.path().join("color/00004.png").display(),
            tmp.path().join("depth/00003.png").display()
        )),
        "{err}"
    );
}

/// A PNG whose header declares `width` x `height` 8-bit RGB pixels, with a valid checksum, and
/// the data of a 1 x 1 image: what a decompression bomb looks like to a decoder before it
/// allocates.
fn png_declaring(width: u32, height: u32) -> Vec<u8> {
    let mut png = Vec::new();
    image::RgbImage::new(1, 1)
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    // Signature (8), IHDR length (4), "IHDR" (4), width, height, ...; the CRC covers the type
    // and the 13 data bytes.
    png[16..20].copy_from_slice(&width.to_be_bytes());
    png[20..24].copy_from_slice(&height.to_be_bytes());
    let crc = crc32fast::hash(&png[12..29]);
    png[29..33].copy_from_slice(&crc.to_be_bytes());
    png
}

#[test]
fn images_declaring_more_pixels_than_the_limit_are_refused_before_decoding() {
    let origin = std::path::Path::new("bomb.png");
    for (w, h) in [(13_000, 13_000), (20_000, 2)] {
        let error = vlem_datasets::colour_from_bytes(&png_declaring(w, h), origin)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(error.contains("bomb.png"), "{w}x{h}: {error}");
        assert!(error.to_lowercase().contains("limit"), "{w}x{h}: {error}");
    }
}

/// A 64 x 48 colour gradient encoded as JPEG.
fn jpeg_bytes() -> Vec<u8> {
    let image = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 4, y as u8 * 5, 90]));
    let mut bytes = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 90)
        .encode_image(&image)
        .unwrap();
    bytes
}

#[test]
fn a_truncated_jpeg_is_refused_naming_the_file() {
    let whole = jpeg_bytes();
    let origin = std::path::Path::new("frame.jpg");
    let decoded = vlem_datasets::colour_from_bytes(&whole, origin).unwrap();
    assert_eq!((decoded.width(), decoded.height()), (64, 48));
    // Padding after the end-of-image marker, as some cameras write, is fine.
    let mut padded = whole.clone();
    padded.extend_from_slice(&[0; 64]);
    assert!(vlem_datasets::colour_from_bytes(&padded, origin).is_ok());
    // Cut inside the scan (the decoder alone fills the rest with grey and says nothing).
    let cut = &whole[..whole.len() * 2 / 3];
    let error = vlem_datasets::colour_from_bytes(cut, origin)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(
        error.starts_with("frame.jpg: cannot decode image"),
        "{error}"
    );
    assert!(error.contains("truncated"), "{error}");

    // In a dataset folder, the frame's file is named.
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 1, false);
    let colour = tmp.path().join("color/00000.png");
    std::fs::write(&colour, cut).unwrap();
    let reader = IclReader::open(tmp.path(), &DatasetConfig::default()).unwrap();
    let err = reader.load(0).unwrap_err().to_string();
    assert!(
        err.starts_with(&format!("{}: cannot decode image", colour.display())),
        "{err}"
    );
}

#[cfg(unix)]
#[test]
fn symlink_loops_dangling_links_and_fifos_are_named() {
    /// Puts something that is not an image file at the path.
    type Setup = fn(&std::path::Path);
    let setups: [(&str, Setup); 3] = [
        ("a symbolic link that cannot be followed", |path| {
            let other = path.with_file_name("loop.lnk");
            std::os::unix::fs::symlink(&other, path).unwrap();
            std::os::unix::fs::symlink(path, &other).unwrap();
        }),
        ("a symbolic link to nothing", |path| {
            std::os::unix::fs::symlink(path.with_file_name("gone.png"), path).unwrap();
        }),
        ("a FIFO (named pipe)", |path| {
            let made = std::process::Command::new("mkfifo")
                .arg(path)
                .status()
                .unwrap();
            assert!(made.success());
        }),
    ];
    for (what, setup) in setups {
        let tmp = tempfile::tempdir().unwrap();
        common::write_icl(tmp.path(), 0, 3, false);
        let colour = tmp.path().join("color/00001.png");
        std::fs::remove_file(&colour).unwrap();
        setup(&colour);
        let err = icl_error(tmp.path());
        assert!(
            err.starts_with(&format!("{}: {what}", colour.display())),
            "{what}: {err}"
        );
        assert!(err.contains("not a regular file"), "{err}");
    }
}

#[test]
fn a_dataset_folders_trajectory_file_is_found_as_its_reader_finds_it() {
    let tmp = tempfile::tempdir().unwrap();
    common::write_icl(tmp.path(), 0, 2, true);
    assert_eq!(
        vlem_datasets::trajectory_file(tmp.path()).unwrap(),
        tmp.path().join("trajectory.log")
    );
    // Another name: the folder's one .log file.
    std::fs::rename(
        tmp.path().join("trajectory.log"),
        tmp.path().join("estimate.log"),
    )
    .unwrap();
    assert_eq!(
        vlem_datasets::trajectory_file(tmp.path()).unwrap(),
        tmp.path().join("estimate.log")
    );
    // None: the error names what was looked for.
    std::fs::remove_file(tmp.path().join("estimate.log")).unwrap();
    let err = vlem_datasets::trajectory_file(tmp.path())
        .unwrap_err()
        .to_string();
    assert!(err.contains("trajectory.log"), "{err}");
}
