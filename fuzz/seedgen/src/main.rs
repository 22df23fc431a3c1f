//! `seedgen IN OUT FORMAT GEOMETRY`: reads the image IN, cuts it down and writes it as OUT.
//!
//! GEOMETRY is `sample:WxH` (nearest-neighbour, so depth values stay real depths) or
//! `crop:WxH+X+Y`. FORMAT is one of `png-gray16`, `png-gray8`, `png-rgb8`, `png-rgba16`,
//! `jpeg-rgb`, `jpeg-gray`, `pgm16`, `ppm`.

use std::io::BufWriter;
use std::process::ExitCode;

use image::codecs::jpeg::JpegEncoder;
use image::codecs::pnm::{PnmEncoder, PnmSubtype, SampleEncoding};
use image::imageops::FilterType;
use image::{DynamicImage, ImageEncoder, ImageFormat};

fn parse_size(s: &str) -> Option<(u32, u32)> {
    let (w, h) = s.split_once('x')?;
    Some((w.parse().ok()?, h.parse().ok()?))
}

fn cut(image: DynamicImage, geometry: &str) -> Result<DynamicImage, String> {
    let bad = || format!("bad geometry `{geometry}`");
    if let Some(size) = geometry.strip_prefix("sample:") {
        let (w, h) = parse_size(size).ok_or_else(bad)?;
        return Ok(image.resize_exact(w, h, FilterType::Nearest));
    }
    let crop = geometry.strip_prefix("crop:").ok_or_else(bad)?;
    let mut parts = crop.split('+');
    let (w, h) = parts.next().and_then(parse_size).ok_or_else(bad)?;
    let x: u32 = parts.next().and_then(|s| s.parse().ok()).ok_or_else(bad)?;
    let y: u32 = parts.next().and_then(|s| s.parse().ok()).ok_or_else(bad)?;
    Ok(image.crop_imm(x, y, w, h))
}

fn pnm<W: std::io::Write>(
    w: W,
    subtype: PnmSubtype,
    image: DynamicImage,
) -> image::ImageResult<()> {
    PnmEncoder::new(w).with_subtype(subtype).write_image(
        image.as_bytes(),
        image.width(),
        image.height(),
        image.color().into(),
    )
}

fn write(image: DynamicImage, out: &str, format: &str) -> Result<(), String> {
    let e = |e: image::ImageError| format!("{out}: {e}");
    let file = || -> Result<_, String> {
        Ok(BufWriter::new(
            std::fs::File::create(out).map_err(|e| format!("{out}: {e}"))?,
        ))
    };
    match format {
        "png-gray16" => {
            DynamicImage::ImageLuma16(image.into_luma16()).save_with_format(out, ImageFormat::Png)
        }
        "png-gray8" => {
            DynamicImage::ImageLuma8(image.into_luma8()).save_with_format(out, ImageFormat::Png)
        }
        "png-rgb8" => {
            DynamicImage::ImageRgb8(image.into_rgb8()).save_with_format(out, ImageFormat::Png)
        }
        "png-rgba16" => {
            DynamicImage::ImageRgba16(image.into_rgba16()).save_with_format(out, ImageFormat::Png)
        }
        "jpeg-rgb" => JpegEncoder::new_with_quality(file()?, 80).encode_image(&image.into_rgb8()),
        "jpeg-gray" => JpegEncoder::new_with_quality(file()?, 80).encode_image(&image.into_luma8()),
        // The PNM encoder writes no 16-bit samples; the format is simple enough to write here.
        "pgm16" => {
            let gray = image.into_luma16();
            let mut bytes = format!("P5\n{} {}\n65535\n", gray.width(), gray.height()).into_bytes();
            gray.as_raw()
                .iter()
                .for_each(|v| bytes.extend_from_slice(&v.to_be_bytes()));
            return std::fs::write(out, bytes).map_err(|e| format!("{out}: {e}"));
        }
        "ppm" => pnm(
            file()?,
            PnmSubtype::Pixmap(SampleEncoding::Binary),
            DynamicImage::ImageRgb8(image.into_rgb8()),
        ),
        other => return Err(format!("unknown format `{other}`")),
    }
    .map_err(e)
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, out, format, geometry] = args.as_slice() else {
        eprintln!("usage: seedgen IN OUT FORMAT GEOMETRY (see the source)");
        return ExitCode::FAILURE;
    };
    let result = image::ImageReader::open(input)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| format!("{input}: {e}"))
        .and_then(|r| r.decode().map_err(|e| format!("{input}: {e}")))
        .and_then(|image| cut(image, geometry))
        .and_then(|image| write(image, out, format));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("seedgen: {message}");
            ExitCode::FAILURE
        }
    }
}
