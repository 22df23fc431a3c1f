#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! The `sam` region proposer: the network against goldens from the reference implementations
//! (`segment-anything` 1.0 and MobileSAM's TinyViT, made by
//! `goldens/sam/make_sam_goldens.py` with the deterministic synthetic weights that
//! `vlem_backends::sam::synthetic` computes), the mask generator and the fill-in refinement with
//! a hand-made decoder, the config and the weights loading.
#![cfg(feature = "sam")]

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use serde_json::Value;
use vlem_backends::sam::image::{
    AxisMap, LOW_RES, preprocess_shape, resize_rgb_like_pillow, upsample_logits,
};
use vlem_backends::sam::model::{EncoderConfig, SamModel};
use vlem_backends::sam::synthetic::{SyntheticWeights, fnv1a64};
use vlem_backends::sam::tiny_vit::TinyVitConfig;
use vlem_backends::sam::vit::VitConfig;
use vlem_backends::sam::{
    self, GeneratedMask, GeneratorParams, MaskFiltering, Pass, SamConfig, SamVariant, amg,
    generate_masks,
};
use vlem_backends::{BackendError, ModelDtype};
use vlem_core::{BuildContext, RgbImage, StageConfig};

fn goldens_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens/sam")
}

fn read_json(name: &str) -> Value {
    let path = goldens_dir().join(name);
    serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap()
}

fn f32s(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

/// The test image of the golden script (`test_image` there).
fn test_image(w: usize, h: usize) -> RgbImage {
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h as i64 {
        for x in 0..w as i64 {
            let (wi, hi) = (w as i64, h as i64);
            let rect = x >= wi / 5 && x < wi / 2 && y >= hi / 4 && y < (3 * hi) / 4;
            let disc = (x - (3 * wi) / 4).pow(2) + (y - hi / 2).pow(2) < (hi / 5).pow(2);
            let rgb = if rect {
                [240, 230, 60]
            } else if disc {
                [20, 30, 200]
            } else {
                [
                    (x * 7 + y * 3).rem_euclid(256),
                    (x * y).rem_euclid(256),
                    (255 - 2 * x + 5 * y).rem_euclid(256),
                ]
            };
            data.extend(rgb.map(|v| v as u8));
        }
    }
    RgbImage::new(w as u32, h as u32, data).unwrap()
}

/// The goldens' image and its size, `(width, height, image)`.
fn golden_image(goldens: &Value) -> (usize, usize, RgbImage) {
    let size = |key: &str| goldens["image"][key].as_u64().unwrap() as usize;
    let (w, h) = (size("width"), size("height"));
    (w, h, test_image(w, h))
}

fn assert_close(what: &str, got: &[f32], want: &[f32], tol: f32) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let (mut worst, mut at) = (0f32, 0);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let d = (g - w).abs();
        if d > worst {
            (worst, at) = (d, i);
        }
    }
    assert!(
        worst <= tol,
        "{what}: max abs error {worst} at {at} (got {}, want {}), tolerance {tol}",
        got[at],
        want[at]
    );
}

#[test]
fn pillow_resize_matches_the_reference_bytes() {
    let goldens = read_json("sam_goldens.json");
    for case in goldens["resize_only"].as_array().unwrap() {
        let size: Vec<usize> = serde_json::from_value(case["size"].clone()).unwrap();
        let want: Vec<usize> = serde_json::from_value(case["resized_size"].clone()).unwrap();
        let (w, h) = (size[0], size[1]);
        let (ih, iw) = preprocess_shape(h, w, 1024);
        assert_eq!([iw, ih], [want[0], want[1]], "resized size of {w}x{h}");
        let image = test_image(w, h);
        let resized = resize_rgb_like_pillow(image.as_raw(), w, h, iw, ih);
        assert_eq!(
            format!("{:016x}", fnv1a64(&resized)),
            case["fnv1a64"].as_str().unwrap(),
            "Pillow bilinear resize of {w}x{h} to {iw}x{ih}"
        );
    }
}

/// Builds `encoder` on synthetic weights and checks that every tensor it reads exists in the
/// reference's state dict `state_dict` with the same shape; returns the model and the names of
/// the reference's tensors it does not read.
fn build_checked(encoder: &EncoderConfig, state_dict: &str) -> (SamModel, Vec<String>) {
    let reference: BTreeMap<String, Vec<usize>> = read_json(state_dict)
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e[0].as_str().unwrap().to_owned(),
                serde_json::from_value(e[1].clone()).unwrap(),
            )
        })
        .collect();
    let weights = SyntheticWeights::new();
    let model = SamModel::new(weights.var_builder(&common::device()), encoder).unwrap();
    let requested = weights.requested();
    for (name, shape) in &requested {
        match reference.get(name) {
            Some(s) => assert_eq!(s, shape, "shape of {name}"),
            None => panic!("{name} is not a tensor of the reference ({state_dict})"),
        }
    }
    let unused = reference
        .keys()
        .filter(|k| !requested.iter().any(|(n, _)| n == *k))
        .cloned()
        .collect();
    (model, unused)
}

/// Tensors of the reference that point prompts never use (mask prompts, background and box
/// points) or that TinyViT only uses for classification.
fn expected_unused(name: &str) -> bool {
    name.starts_with("prompt_encoder.mask_downscaling.")
        || name.starts_with("prompt_encoder.point_embeddings.0.")
        || name.starts_with("prompt_encoder.point_embeddings.2.")
        || name.starts_with("prompt_encoder.point_embeddings.3.")
        || name.starts_with("image_encoder.norm_head.")
        || name.starts_with("image_encoder.head.")
}

fn multimask(model: &SamModel, emb: &Tensor, points: &[[f32; 2]]) -> (Vec<f32>, Vec<f32>) {
    let (masks, ious) = model.decode_points(emb, points).unwrap();
    let masks = masks.narrow(1, 1, 3).unwrap().flatten_all().unwrap();
    let ious = ious.narrow(1, 1, 3).unwrap().flatten_all().unwrap();
    let f32s = |t: Tensor| t.to_dtype(DType::F32).unwrap().to_vec1().unwrap();
    (f32s(masks), f32s(ious))
}

fn stride_sample(values: &[f32], width: usize, step: usize) -> Vec<f32> {
    let height = values.len() / width;
    (0..height)
        .step_by(step)
        .flat_map(|y| (0..width).step_by(step).map(move |x| values[y * width + x]))
        .collect()
}

/// Low-resolution mask logits and embeddings are O(1); these bounds leave room for f32
/// summation-order differences between candle and PyTorch through a dozen layers.
fn embed_tol() -> f32 {
    common::tolerance(1e-4)
}
fn mask_tol() -> f32 {
    common::tolerance(1e-4)
}

fn check_network(key: &str, encoder: EncoderConfig, state_dict: &str) {
    let goldens = read_json("sam_goldens.json");
    let g = &goldens[key];
    let (model, unused) = build_checked(&encoder, state_dict);
    let unexpected: Vec<&String> = unused.iter().filter(|n| !expected_unused(n)).collect();
    assert!(unexpected.is_empty(), "tensors never read: {unexpected:?}");

    let (w, h, image) = golden_image(&goldens);
    let pre = model.preprocess(image.as_raw(), w, h).unwrap();
    assert_eq!(
        [pre.input.1, pre.input.0],
        [
            g["resized_size"][0].as_u64().unwrap() as usize,
            g["resized_size"][1].as_u64().unwrap() as usize
        ]
    );
    assert_eq!(
        format!("{:016x}", fnv1a64(&pre.resized)),
        g["resized_fnv1a64"].as_str().unwrap()
    );
    let input_sum = pre.tensor.sum_all().unwrap().to_scalar::<f32>().unwrap();
    let want_sum = g["input_sum"].as_f64().unwrap() as f32;
    // Sums of 3M f32 values in different orders: a loose bound (the bytes are checked above).
    assert!(
        (input_sum - want_sum).abs() <= 1e-3 * want_sum.abs().max(1.0),
        "input sum {input_sum} vs {want_sum}"
    );

    let emb = model.embed(&pre.tensor).unwrap();
    assert_eq!(emb.dims(), &[1, 256, 64, 64]);
    let values: Vec<f32> = emb.flatten_all().unwrap().to_vec1().unwrap();
    // f64 sums: a million f32 additions in sequence drift by more than the tolerance.
    let n = values.len() as f64;
    let mean = (values.iter().map(|&v| f64::from(v)).sum::<f64>() / n) as f32;
    let abs_mean = (values.iter().map(|&v| f64::from(v.abs())).sum::<f64>() / n) as f32;
    let want_mean = g["embedding_mean"].as_f64().unwrap() as f32;
    let want_abs = g["embedding_abs_mean"].as_f64().unwrap() as f32;
    assert!(
        (mean - want_mean).abs() < common::tolerance(1e-5),
        "{key}: mean {mean} vs {want_mean}"
    );
    assert!(
        (abs_mean - want_abs).abs() < common::tolerance(1e-5),
        "{key}: mean |x| {abs_mean} vs {want_abs}"
    );
    let sample: Vec<f32> = (0..256)
        .step_by(32)
        .flat_map(|c| {
            let values = &values;
            (0..64).step_by(8).flat_map(move |y| {
                (0..64)
                    .step_by(8)
                    .map(move |x| values[c * 4096 + y * 64 + x])
            })
        })
        .collect();
    assert_close(
        &format!("{key} embeddings"),
        &sample,
        &f32s(&g["embedding_sample"]),
        embed_tol(),
    );

    let xs = AxisMap::new(pre.input.1, w);
    let ys = AxisMap::new(pre.input.0, h);
    for p in g["points"].as_array().unwrap() {
        let pt = f32s(&p["point"]);
        let input_pt = [
            (f64::from(pt[0]) * pre.input.1 as f64 / w as f64) as f32,
            (f64::from(pt[1]) * pre.input.0 as f64 / h as f64) as f32,
        ];
        let (masks, ious) = multimask(&model, &emb, &[input_pt]);
        assert_close(
            &format!("{key} IoU at {pt:?}"),
            &ious,
            &f32s(&p["iou"]),
            mask_tol(),
        );
        for k in 0..3 {
            let low = &masks[k * LOW_RES * LOW_RES..(k + 1) * LOW_RES * LOW_RES];
            let gl = &p["low_res"][k];
            assert_close(
                &format!("{key} low-res mask {k} at {pt:?}"),
                &stride_sample(low, LOW_RES, 16),
                &f32s(&gl["sample"]),
                mask_tol(),
            );
            let up = upsample_logits(low, &xs, &ys);
            let gu = &p["upsampled"][k];
            assert_close(
                &format!("{key} upsampled mask {k} at {pt:?}"),
                &stride_sample(&up, w, 8),
                &f32s(&gu["sample"]),
                mask_tol(),
            );
            let stability = amg::stability_score(&up, 0.0, 1.0);
            assert!(
                (stability - gu["stability_score"].as_f64().unwrap() as f32).abs() < 1e-6,
                "stability"
            );
            let binary: Vec<bool> = up.iter().map(|&l| l > 0.0).collect();
            let area = binary.iter().filter(|&&b| b).count() as i64;
            let want_area = gu["area"].as_i64().unwrap();
            // Pixels whose logit is within float noise of 0 may flip.
            assert!((area - want_area).abs() <= 2, "area {area} vs {want_area}");
            let want_box: Option<[u32; 4]> = serde_json::from_value(gu["box"].clone()).unwrap();
            assert_eq!(amg::mask_to_box(&binary, w), want_box, "box");
        }
    }

    // The automatic mask generator, record by record.
    for run in g["amg"].as_array().unwrap() {
        let rp = &run["params"];
        let params = GeneratorParams {
            points_per_side: rp["points_per_side"].as_u64().unwrap() as usize,
            points_per_batch: 8,
            pred_iou_thresh: rp["pred_iou_thresh"].as_f64().unwrap() as f32,
            stability_score_thresh: rp["stability_score_thresh"].as_f64().unwrap() as f32,
            stability_score_offset: rp["stability_score_offset"].as_f64().unwrap() as f32,
            box_nms_thresh: rp["box_nms_thresh"].as_f64().unwrap() as f32,
            min_mask_region_area: rp["min_mask_region_area"].as_u64().unwrap() as usize,
            refine: false,
            refine_points: 0,
            seed: 0,
        };
        let mut decode = |points: &[[f32; 2]]| -> Decoded { Ok(multimask(&model, &emb, points)) };
        let masks = generate_masks(&params, (w, h), pre.input, &mut decode).unwrap();
        let want = run["masks"].as_array().unwrap();
        assert_eq!(masks.len(), want.len(), "{key} AMG {params:?}: mask count");
        // Compare as sets keyed by (point, predicted IoU): the order of equal NMS scores is
        // not specified by the reference's sort.
        let key_of = |point: [f64; 2], iou: f32| {
            (
                (point[0] * 4.0) as i64,
                (point[1] * 4.0) as i64,
                (iou * 1e3).round() as i64,
            )
        };
        for wm in want {
            let wp = f32s(&wm["point"]);
            let wiou = wm["predicted_iou"].as_f64().unwrap() as f32;
            let k = key_of([f64::from(wp[0]), f64::from(wp[1])], wiou);
            let got: &GeneratedMask = masks
                .iter()
                .find(|m| key_of(m.point, m.predicted_iou) == k)
                .unwrap_or_else(|| panic!("{key} AMG: no mask for {wm}"));
            assert!((got.predicted_iou - wiou).abs() < mask_tol());
            let ws = wm["stability_score"].as_f64().unwrap() as f32;
            assert!(
                (got.stability_score - ws).abs() < 2e-3,
                "{key} AMG stability {} vs {ws}",
                got.stability_score
            );
            let wa = wm["area"].as_i64().unwrap();
            assert!(
                (got.area() as i64 - wa).abs() <= 3,
                "{key} AMG area {} vs {wa} ({params:?})",
                got.area()
            );
            let [x0, y0, x1, y1] = got.bbox;
            let wb: Vec<u32> = serde_json::from_value(wm["bbox"].clone()).unwrap();
            assert_eq!(vec![x0, y0, x1 - x0, y1 - y0], wb, "{key} AMG box (XYWH)");
        }
        if params.min_mask_region_area == 0 {
            // Distinct scores: the reference's order (by decreasing predicted IoU) is ours.
            let got: Vec<f32> = masks.iter().map(|m| m.predicted_iou).collect();
            let want: Vec<f32> = want
                .iter()
                .map(|m| m["predicted_iou"].as_f64().unwrap() as f32)
                .collect();
            assert_close(&format!("{key} AMG order"), &got, &want, mask_tol());
        }
    }
}

/// The tiny ViT of the goldens.
fn tiny_vit() -> EncoderConfig {
    EncoderConfig::Vit(VitConfig {
        embed_dim: 32,
        depth: 2,
        num_heads: 2,
        global_attn_indexes: vec![1],
    })
}

/// The tiny TinyViT of the goldens.
fn tiny_tinyvit() -> EncoderConfig {
    EncoderConfig::TinyVit(TinyVitConfig {
        embed_dims: [16, 32, 64, 320],
        depths: [1, 1, 1, 1],
        num_heads: [1, 2, 2, 10],
        window_sizes: [7, 7, 14, 7],
    })
}

#[test]
fn vit_network_matches_segment_anything() {
    check_network("vit", tiny_vit(), "state_dict_tiny_vit.json");
}

#[test]
fn tinyvit_network_matches_mobile_sam() {
    check_network("tiny_vit", tiny_tinyvit(), "state_dict_tiny_tinyvit.json");
}

/// Half precision (`dtype = "f16" | "bf16"`): both networks on the goldens' weights and image,
/// against the f32 network (which `check_network` holds to the references): the image embedding
/// per grid cell (cosine), and per golden point each multimask mask, upsampled to the image and
/// cut at 0, by its IoU with the f32 network's mask, and the predicted IoUs.
#[test]
fn half_precision_networks_agree_with_f32() {
    let goldens = read_json("sam_goldens.json");
    let (w, h, image) = golden_image(&goldens);
    // (batch, 256, 64, 64) -> one row of 256 per grid cell.
    let cells = |t: &Tensor| -> Vec<f32> {
        let t = t
            .to_dtype(DType::F32)
            .unwrap()
            .reshape((256, 4096))
            .unwrap();
        t.t().unwrap().flatten_all().unwrap().to_vec1().unwrap()
    };
    for (key, encoder) in [("vit", tiny_vit()), ("tiny_vit", tiny_tinyvit())] {
        let full = SamModel::new(
            SyntheticWeights::new().var_builder(&common::device()),
            &encoder,
        )
        .unwrap();
        let pre = full.preprocess(image.as_raw(), w, h).unwrap();
        let emb_full = full.embed(&pre.tensor).unwrap();
        let (xs, ys) = (AxisMap::new(pre.input.1, w), AxisMap::new(pre.input.0, h));
        // candle has no bf16 convolutions on the CPU: bf16 is checked on a GPU
        // (`VLEM_TEST_DEVICE=cuda`), and refused on the CPU (below).
        let dtypes = match common::compute_device() {
            vlem_backends::ComputeDevice::Cpu => vec![(ModelDtype::F16, 0.01)],
            _ => vec![(ModelDtype::F16, 0.01), (ModelDtype::Bf16, 0.05)],
        };
        for (dtype, iou_tol) in dtypes {
            let vb = SyntheticWeights::new().var_builder_in(&common::device(), dtype.candle());
            let half = SamModel::new(vb, &encoder).unwrap();
            let emb = half.embed(&pre.tensor).unwrap();
            assert_eq!(emb.dtype(), dtype.candle());
            let cosine = common::least_row_cosine(&cells(&emb), &cells(&emb_full), 256);
            let mut least_iou = 1.0f32;
            let mut worst_pred = 0.0f32;
            for p in goldens[key]["points"].as_array().unwrap() {
                let pt = f32s(&p["point"]);
                let input_pt = [
                    pt[0] * pre.input.1 as f32 / w as f32,
                    pt[1] * pre.input.0 as f32 / h as f32,
                ];
                let (masks_full, ious_full) = multimask(&full, &emb_full, &[input_pt]);
                let (masks, ious) = multimask(&half, &emb, &[input_pt]);
                for k in 0..3 {
                    let range = k * LOW_RES * LOW_RES..(k + 1) * LOW_RES * LOW_RES;
                    let a = upsample_logits(&masks[range.clone()], &xs, &ys);
                    let b = upsample_logits(&masks_full[range], &xs, &ys);
                    let both = a.iter().zip(&b).filter(|(x, y)| **x > 0.0 && **y > 0.0);
                    let either = a.iter().zip(&b).filter(|(x, y)| **x > 0.0 || **y > 0.0);
                    let (both, either) = (both.count(), either.count());
                    if either > 0 {
                        least_iou = least_iou.min(both as f32 / either as f32);
                    }
                    worst_pred = worst_pred.max((ious[k] - ious_full[k]).abs());
                }
            }
            println!(
                "{key} {dtype:?}: least embedding cosine {cosine:.6}, least mask IoU \
                 {least_iou:.4}, largest predicted-IoU difference {worst_pred:.4}"
            );
            let bound = common::half_precision_bound(dtype);
            assert!(
                cosine >= bound,
                "{key} {dtype:?}: embedding cosine {cosine}"
            );
            assert!(least_iou >= 0.98, "{key} {dtype:?}: mask IoU {least_iou}");
            assert!(
                worst_pred <= iou_tol,
                "{key} {dtype:?}: predicted IoU off by {worst_pred}"
            );
        }
    }
    let vb = SyntheticWeights::new().var_builder_in(&Device::Cpu, DType::BF16);
    let e = SamModel::new(vb, &tiny_vit()).unwrap_err().to_string();
    assert!(e.contains("bf16") && e.contains("GPU"), "{e}");
}

/// The generator's filters on the model's device (`MaskFiltering::Device`, a GPU's path, here on
/// candle's CPU device: thresholds, boxes, masks held through NMS, one copy of the kept) against
/// the host's: the same masks, with the thresholds set so that each filter drops some, NMS off
/// and then dropping some, the refinement and small-region removal on.
#[test]
fn device_filtering_gives_the_host_filterings_masks() {
    let goldens = read_json("sam_goldens.json");
    let (_, _, image) = golden_image(&goldens);
    for (key, encoder) in [("vit", tiny_vit()), ("tiny_vit", tiny_tinyvit())] {
        let model = SamModel::new(
            SyntheticWeights::new().var_builder(&common::device()),
            &encoder,
        )
        .unwrap();
        let open = GeneratorParams {
            points_per_side: 4,
            points_per_batch: 5,
            pred_iou_thresh: 0.0,
            stability_score_thresh: 0.0,
            // The synthetic network's logits are small: a small offset spreads the stabilities.
            stability_score_offset: 0.05,
            box_nms_thresh: 1.0,
            min_mask_region_area: 0,
            refine: false,
            ..GeneratorParams::default()
        };
        let proposer = sam::SamProposer::new(model, open.clone());
        let all = proposer.generate_with(&image, MaskFiltering::Host).unwrap();
        let mut ious: Vec<f32> = all.iter().map(|m| m.predicted_iou).collect();
        let mut stabilities: Vec<f32> = all.iter().map(|m| m.stability_score).collect();
        ious.sort_by(f32::total_cmp);
        stabilities.sort_by(f32::total_cmp);
        let (model, _) = proposer.into_parts();
        let filters = GeneratorParams {
            pred_iou_thresh: ious[ious.len() / 3],
            stability_score_thresh: stabilities[stabilities.len() / 3],
            min_mask_region_area: 40,
            refine: true,
            refine_points: 6,
            ..open.clone()
        };
        // Many of the synthetic masks share a box (the ViT's all span the image), so NMS at
        // 0.99 drops many; without the thresholds MobileSAM's kept ones come from several
        // batches, in another order than decoded.
        let nms = GeneratorParams {
            box_nms_thresh: 0.99,
            ..open
        };
        let mut model = Some(model);
        for (what, params) in [("thresholds", filters), ("NMS", nms)] {
            let Some(network) = model.take() else { break };
            let proposer = sam::SamProposer::new(network, params.clone());
            let host = proposer.generate_with(&image, MaskFiltering::Host).unwrap();
            let device = proposer
                .generate_with(&image, MaskFiltering::Device)
                .unwrap();
            let grid = host.iter().filter(|m| m.pass == Pass::Grid).count();
            println!(
                "{key}, {what}: {} masks unfiltered; filtered on the host {} ({grid} of the \
                 grid), on the device {}",
                all.len(),
                host.len(),
                device.len()
            );
            assert!(
                grid > 0 && grid < all.len(),
                "{key}: the {what} dropped none or all"
            );
            assert_eq!(host.len(), device.len(), "{key}: mask count");
            for (a, b) in host.iter().zip(&device) {
                assert_eq!((a.point, a.pass), (b.point, b.pass), "{key}: order");
                assert_eq!(a.predicted_iou, b.predicted_iou, "{key}: predicted IoU");
                assert!(
                    (a.stability_score - b.stability_score).abs() < 1e-3,
                    "{key}: stability"
                );
                assert_eq!(a.bbox, b.bbox, "{key}: box");
                let differ = a.mask.iter().zip(&b.mask).filter(|(x, y)| x != y).count();
                assert!(differ <= 2, "{key}: {differ} pixels differ");
            }
            model = Some(proposer.into_parts().0);
        }
    }
}

#[test]
fn full_size_architectures_read_the_official_tensor_names() {
    for (variant, file) in [
        (SamVariant::MobileSam, "state_dict_mobile_sam.json"),
        (SamVariant::VitB, "state_dict_vit_b.json"),
    ] {
        let (_, unused) = build_checked(&variant.encoder(), file);
        let unexpected: Vec<&String> = unused.iter().filter(|n| !expected_unused(n)).collect();
        assert!(
            unexpected.is_empty(),
            "{variant:?}: never read: {unexpected:?}"
        );
    }
}

// ---------------------------------------------------------------- generator with a fake decoder

/// What a decoder returns: mask logits and IoU predictions.
type Decoded = Result<(Vec<f32>, Vec<f32>), BackendError>;

/// A decoder that answers every prompt with three copies of a disc of `radius` low-res pixels
/// around the prompt (logits +8 inside, -8 outside), predicted IoU 0.95, 0.9 and 0.5.
fn disc_decoder(radius: f32) -> impl FnMut(&[[f32; 2]]) -> Decoded {
    move |points: &[[f32; 2]]| {
        let mut masks = Vec::with_capacity(points.len() * 3 * LOW_RES * LOW_RES);
        let mut ious = Vec::with_capacity(points.len() * 3);
        for p in points {
            // Input (1024-scale) pixels to low-res pixels.
            let (cx, cy) = ((p[0] + 0.5) / 4.0, (p[1] + 0.5) / 4.0);
            for iou in [0.95, 0.9, 0.5] {
                for y in 0..LOW_RES {
                    for x in 0..LOW_RES {
                        let d =
                            ((x as f32 + 0.5 - cx).powi(2) + (y as f32 + 0.5 - cy).powi(2)).sqrt();
                        masks.push(if d < radius { 8.0 } else { -8.0 });
                    }
                }
                ious.push(iou);
            }
        }
        Ok((masks, ious))
    }
}

fn params(points_per_side: usize, refine: bool) -> GeneratorParams {
    GeneratorParams {
        points_per_side,
        points_per_batch: 3,
        refine,
        refine_points: 16,
        seed: 3,
        ..GeneratorParams::default()
    }
}

#[test]
fn generator_keeps_one_mask_per_object_and_filters_by_predicted_iou() {
    // 256 x 192 image (input 1024 x 768): a 2 x 2 grid gives four separate discs of radius
    // 12 low-res pixels = 12 image pixels.
    let mut decode = disc_decoder(12.0);
    let masks = generate_masks(&params(2, false), (256, 192), (768, 1024), &mut decode).unwrap();
    assert_eq!(
        masks.len(),
        4,
        "the three outputs of a point are duplicates"
    );
    for m in &masks {
        assert_eq!(m.predicted_iou, 0.95, "the best-predicted copy wins");
        assert!(m.pass == Pass::Grid);
        // A disc of radius 12 px has ~452 pixels.
        assert!((400..=500).contains(&m.area()), "area {}", m.area());
        let r = m.to_region();
        assert!(
            r.contains(m.point[0] as u32, m.point[1] as u32),
            "covers its prompt"
        );
        assert_eq!(r.mask.len(), (r.bbox.width * r.bbox.height) as usize);
    }
    // A predicted-IoU threshold above every prediction leaves nothing.
    let strict = GeneratorParams {
        pred_iou_thresh: 0.96,
        ..params(2, false)
    };
    assert!(
        generate_masks(&strict, (256, 192), (768, 1024), &mut decode)
            .unwrap()
            .is_empty()
    );
}

#[test]
fn refinement_fills_uncovered_areas_and_can_be_turned_off() {
    let mut decode = disc_decoder(12.0);
    let without = generate_masks(&params(2, false), (256, 192), (768, 1024), &mut decode).unwrap();
    let with = generate_masks(&params(2, true), (256, 192), (768, 1024), &mut decode).unwrap();
    assert_eq!(&with[..without.len()], &without[..], "first pass unchanged");
    let fill: Vec<&GeneratedMask> = with.iter().filter(|m| m.pass == Pass::Refine).collect();
    assert!(fill.len() >= 8, "{} fill-in masks", fill.len());
    let mut covered = vec![false; 256 * 192];
    for m in &without {
        for (i, c) in covered.iter_mut().enumerate() {
            *c |= m.to_region().contains((i % 256) as u32, (i / 256) as u32);
        }
    }
    for m in &fill {
        let [x, y] = m.point;
        assert!(
            !covered[y as usize * 256 + x as usize],
            "fill-in prompts lie in uncovered pixels"
        );
        assert!(m.to_region().contains(x as u32, y as u32));
        // No fill-in mask duplicates a kept one.
        for k in &without {
            assert!(amg::box_iou(&k.bbox, &m.bbox) <= 0.7);
        }
    }
    // Seeded: the same masks again; another seed draws other points.
    let again = generate_masks(&params(2, true), (256, 192), (768, 1024), &mut decode).unwrap();
    assert_eq!(with, again);
    let other = GeneratorParams {
        seed: 4,
        ..params(2, true)
    };
    let other = generate_masks(&other, (256, 192), (768, 1024), &mut decode).unwrap();
    assert_ne!(with, other);
}

#[test]
fn small_region_removal_drops_specks_from_masks() {
    // One prompt; the decoder's masks are a disc plus a 1-low-res-pixel speck far away, which
    // upsamples to a few image pixels.
    let mut decode = |points: &[[f32; 2]]| -> Decoded {
        let (mut masks, ious) = disc_decoder(20.0)(points)?;
        for k in 0..points.len() * 3 {
            masks[k * LOW_RES * LOW_RES + 250 * LOW_RES + 250] = 8.0;
        }
        Ok((masks, ious))
    };
    let base = GeneratorParams {
        refine: false,
        ..params(1, false)
    };
    let plain = generate_masks(&base, (256, 256), (1024, 1024), &mut decode).unwrap();
    assert_eq!(plain.len(), 1);
    let cleaned = GeneratorParams {
        min_mask_region_area: 50,
        ..base
    };
    let cleaned = generate_masks(&cleaned, (256, 256), (1024, 1024), &mut decode).unwrap();
    assert_eq!(cleaned.len(), 1);
    assert!(cleaned[0].area() < plain[0].area(), "the speck is gone");
    assert!(plain[0].bbox[2] >= 249, "the speck widened the box");
    assert!(cleaned[0].bbox[2] < 160, "box {:?}", cleaned[0].bbox);
}

// ---------------------------------------------------------------- config and weights

fn stage(toml_text: &str) -> StageConfig {
    toml::from_str(toml_text).unwrap()
}

fn build_error(toml_text: &str, ctx: &BuildContext) -> String {
    let registry = vlem_core::Registry::global().unwrap();
    match registry.build_proposer(&stage(toml_text), ctx) {
        Ok(_) => panic!("building {toml_text:?} succeeded"),
        Err(e) => {
            use std::error::Error;
            let mut text = e.to_string();
            let mut source = e.source();
            while let Some(s) = source {
                text.push_str(&format!(" / {s}"));
                source = s.source();
            }
            text
        }
    }
}

#[test]
fn config_defaults_and_refusals() {
    let c: SamConfig = toml::from_str("weights = \"w.safetensors\"").unwrap();
    assert_eq!(c.variant, SamVariant::MobileSam);
    assert_eq!(c.generator.points_per_side, 32);
    assert!(c.generator.refine);
    assert_eq!(c.generator.refine_points, 32);
    c.generator.check().unwrap();
    assert_eq!(c.generator, GeneratorParams::default());
    assert_eq!(c.dtype, ModelDtype::F32);
    let c: SamConfig =
        toml::from_str("variant = \"vit-b\"\nrefine = false\ndtype = \"bf16\"").unwrap();
    assert_eq!(c.variant, SamVariant::VitB);
    assert!(!c.generator.refine);
    assert_eq!(c.dtype, ModelDtype::Bf16);

    let ctx = BuildContext::default();
    let e = build_error("kind = \"sam\"\nweights = \"w\"\npoints = 3", &ctx);
    assert!(e.contains("unknown field `points`"), "{e}");
    let e = build_error("kind = \"sam\"\nvariant = \"vit-z\"", &ctx);
    assert!(e.contains("vit-z"), "{e}");
    let e = build_error("kind = \"sam\"\nweights = \"w\"\npoints_per_side = 0", &ctx);
    assert!(e.contains("points_per_side must be in 1..=256"), "{e}");
    let e = build_error(
        "kind = \"sam\"\nweights = \"w\"\npred_iou_thresh = 1.5",
        &ctx,
    );
    assert!(e.contains("pred_iou_thresh must be in [0, 1]"), "{e}");
    let e = build_error(
        "kind = \"sam\"\nweights = \"w\"\ndtype = \"bf16\"\ndevice = \"cpu\"",
        &ctx,
    );
    assert!(e.contains("bf16") && e.contains("\"f16\""), "{e}");
    let e = build_error("kind = \"sam\"", &ctx);
    assert!(
        e.contains("`weights` must name the MobileSAM weights"),
        "{e}"
    );
}

#[test]
fn missing_weights_name_the_file_and_how_to_get_it() {
    let dir = tempfile::tempdir().unwrap();
    let ctx = BuildContext {
        config_dir: dir.path().to_path_buf(),
        ..BuildContext::default()
    };
    let e = build_error(
        "kind = \"sam\"\nweights = \"models/sam_vit_b.safetensors\"\nvariant = \"vit-b\"",
        &ctx,
    );
    let path = dir.path().join("models/sam_vit_b.safetensors");
    assert!(e.contains(&path.display().to_string()), "{e}");
    assert!(e.contains("SAM ViT-B"), "{e}");
    assert!(
        e.contains("https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth"),
        "{e}"
    );
    assert!(
        e.contains("convert_checkpoint.py sam_vit_b_01ec64.pth"),
        "{e}"
    );
    let e = build_error("kind = \"sam\"\nweights = \"m.safetensors\"", &ctx);
    assert!(
        e.contains("MobileSAM/raw/master/weights/mobile_sam.pt"),
        "{e}"
    );

    // A file that is not safetensors is refused with its path.
    std::fs::write(dir.path().join("bad.safetensors"), b"not safetensors").unwrap();
    let e = build_error("kind = \"sam\"\nweights = \"bad.safetensors\"", &ctx);
    assert!(
        e.contains("bad.safetensors") && e.contains("safetensors"),
        "{e}"
    );
}

#[test]
fn converted_mobile_sam_weights_load_and_propose_regions() {
    // Write full-size MobileSAM weights (synthetic values, official names) as safetensors, as
    // convert_checkpoint.py would, then build through the registry and propose.
    let weights = SyntheticWeights::new();
    let encoder = SamVariant::MobileSam.encoder();
    SamModel::new(weights.var_builder(&Device::Cpu), &encoder).unwrap();
    let tensors: std::collections::HashMap<String, Tensor> = weights
        .requested()
        .into_iter()
        .map(|(name, shape)| {
            let values = sam::synthetic::synthetic_values(&name, &shape);
            (name, Tensor::from_vec(values, shape, &Device::Cpu).unwrap())
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    candle_core::safetensors::save(&tensors, dir.path().join("mobile_sam.safetensors")).unwrap();

    let ctx = BuildContext {
        config_dir: dir.path().to_path_buf(),
        ..BuildContext::default()
    };
    // Thresholds off, so that the speckled masks of random weights get through.
    let config = stage(
        "kind = \"sam\"\nweights = \"mobile_sam.safetensors\"\nvariant = \"mobile-sam\"\n\
         points_per_side = 2\npred_iou_thresh = 0.0\nstability_score_thresh = 0.0\n\
         box_nms_thresh = 1.0\nrefine_points = 4",
    );
    let proposer = vlem_core::Registry::global()
        .unwrap()
        .build_proposer(&config, &ctx)
        .unwrap();
    assert_eq!(proposer.name(), "sam");
    let image = test_image(80, 60);
    let regions = proposer.propose(&image).unwrap();
    assert!(!regions.is_empty());
    assert!(regions.len() <= 4 * 3 + 4 * 3, "{} regions", regions.len());
    for r in &regions {
        let b = r.bbox;
        assert!(b.width > 0 && b.height > 0);
        assert!(b.x + b.width <= 80 && b.y + b.height <= 60, "{b:?}");
        assert_eq!(r.mask.len(), (b.width * b.height) as usize);
        assert!(r.area() > 0);
    }
}
