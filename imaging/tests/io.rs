//! Round trips, encoding rules and error reporting of `lightrig_imaging::io`.

use std::path::PathBuf;

use lightrig_imaging::io::{
    decode, linear_to_srgb, read, read_exr_layers, read_exr_rows, read_rows, read_stack, read_with,
    srgb_to_linear, write_exr, write_exr_layers, write_png, write_png_with, write_tiff, write_tiff_with,
    BitDepth, Encoding, ExrPrecision, Image, IoError, Layer, ReadOptions, WriteOptions,
};

/// A fresh directory per test under the system temp dir.
fn temp_dir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lightrig-io-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// An image whose samples walk through every `levels`-step value, so all codes are exercised.
fn ramp(width: u32, height: u32, channels: u8, levels: u32) -> Image {
    Image::from_fn(width, height, channels, |x, y, c| {
        let i = (y * width + x) * u32::from(channels) + u32::from(c);
        (i % (levels + 1)) as f32 / levels as f32
    })
}

fn srgb(image: Image) -> Image {
    image.with_encoding(Encoding::Srgb)
}

#[test]
fn png_and_tiff_8_bit_round_trip_exactly() {
    let dir = temp_dir("int8");
    for channels in 1..=4u8 {
        let image = srgb(ramp(37, 11, channels, 255));
        let png = dir.join(format!("c{channels}.png"));
        write_png(&png, &image, BitDepth::Eight).unwrap();
        assert_eq!(read(&png).unwrap(), image, "PNG with {channels} channels");
        if channels != 2 {
            let tif = dir.join(format!("c{channels}.tif"));
            write_tiff(&tif, &image, BitDepth::Eight).unwrap();
            assert_eq!(read(&tif).unwrap(), image, "TIFF with {channels} channels");
        }
    }
}

#[test]
fn png_and_tiff_16_bit_keep_every_code() {
    let dir = temp_dir("int16");
    // 256 x 256 gray = all 65536 codes once.
    let image = srgb(ramp(256, 256, 1, 65535));
    for name in ["all.png", "all.tif"] {
        let path = dir.join(name);
        if name.ends_with("png") {
            write_png(&path, &image, BitDepth::Sixteen).unwrap();
        } else {
            write_tiff(&path, &image, BitDepth::Sixteen).unwrap();
        }
        let back = read(&path).unwrap();
        assert_eq!(back, image, "{name}");
        let codes: Vec<u32> = back.data.iter().map(|v| (v * 65535.0).round() as u32).collect();
        assert_eq!(codes, (0..65536).collect::<Vec<_>>());
    }
    for channels in [2u8, 3, 4] {
        let image = srgb(ramp(19, 7, channels, 65535));
        let png = dir.join(format!("c{channels}.png"));
        write_png(&png, &image, BitDepth::Sixteen).unwrap();
        assert_eq!(read(&png).unwrap(), image);
    }
}

#[test]
fn linear_16_bit_tiff_needs_the_caller_to_say_linear() {
    let dir = temp_dir("lin16");
    let image = ramp(16, 4, 3, 65535);
    let path = dir.join("camera.tif");
    write_tiff(&path, &image, BitDepth::Sixteen).unwrap();
    let assumed = read(&path).unwrap();
    assert_eq!(assumed.encoding, Encoding::Srgb, "integer files default to sRGB");
    let opts = ReadOptions { assume: Encoding::Linear, ..ReadOptions::default() };
    assert_eq!(read_with(&path, opts).unwrap(), image);
}

#[test]
fn linear_image_to_8_bit_is_refused_unless_encoded() {
    let dir = temp_dir("rule");
    let linear = Image::from_fn(4, 4, 3, |x, _, _| x as f32 / 3.0);
    let path = dir.join("out.png");
    for result in [
        write_png(&path, &linear, BitDepth::Eight),
        write_tiff(dir.join("out.tif"), &linear, BitDepth::Eight),
    ] {
        match result {
            Err(e @ IoError::Encoding { .. }) => assert!(e.to_string().contains("linear"), "{e}"),
            other => panic!("expected an Encoding error, got {other:?}"),
        }
    }
    assert!(!path.exists(), "nothing written on refusal");

    let opts = WriteOptions { encode_srgb: true };
    write_png_with(&path, &linear, BitDepth::Eight, opts).unwrap();
    let back = read(&path).unwrap();
    assert_eq!(back.encoding, Encoding::Srgb);
    let expected = linear.to_srgb();
    for (a, b) in back.data.iter().zip(&expected.data) {
        assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6, "{a} vs {b}");
    }
    // Linear at 16 bits is stored as-is.
    let p16 = dir.join("lin16.tif");
    write_tiff_with(&p16, &linear, BitDepth::Sixteen, WriteOptions::default()).unwrap();
    let back = read_with(&p16, ReadOptions { assume: Encoding::Linear, expect_depth: None }).unwrap();
    for (a, b) in back.data.iter().zip(&linear.data) {
        assert!((a - b).abs() <= 0.5 / 65535.0 + 1e-7);
    }
}

#[test]
fn out_of_range_samples_clamp_when_quantised() {
    let dir = temp_dir("clamp");
    let mut image = srgb(Image::new(3, 1, 1));
    image.data = vec![-0.5, 2.0, f32::NAN];
    let path = dir.join("clamp.png");
    write_png(&path, &image, BitDepth::Eight).unwrap();
    assert_eq!(read(&path).unwrap().data, vec![0.0, 1.0, 0.0]);
}

#[test]
fn srgb_transfer_function_matches_the_standard() {
    // Linear segment and knees.
    assert_eq!(linear_to_srgb(0.0), 0.0);
    assert!((linear_to_srgb(0.0031308) - 0.0031308 * 12.92).abs() < 1e-7);
    assert!((srgb_to_linear(0.04045) - 0.04045 / 12.92).abs() < 1e-7);
    // Both pieces meet at the knee (continuity within float precision).
    let above = 1.055 * 0.0031308f64.powf(1.0 / 2.4) - 0.055;
    assert!((above - 0.0031308 * 12.92).abs() < 1e-5);
    // Reference values.
    assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-6);
    assert!((linear_to_srgb(0.18) - 0.461_356).abs() < 1e-5);
    assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
    assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
    // Round trip.
    for i in 0..=10_000 {
        let v = i as f32 / 10_000.0;
        assert!((srgb_to_linear(linear_to_srgb(v)) - v).abs() < 1e-6, "{v}");
        assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-6, "{v}");
    }
    assert!((srgb_to_linear(-0.5) + srgb_to_linear(0.5)).abs() < 1e-7, "odd-symmetric");
}

#[test]
fn conversions_follow_the_encoding_and_spare_alpha() {
    let linear = Image::from_fn(2, 1, 4, |x, _, c| if c == 3 { 0.25 } else { x as f32 * 0.5 });
    let encoded = linear.to_srgb();
    assert_eq!(encoded.encoding, Encoding::Srgb);
    assert_eq!(encoded.get(1, 0, 0), linear_to_srgb(0.5));
    assert_eq!(encoded.get(1, 0, 3), 0.25, "alpha untouched");
    assert_eq!(encoded.to_srgb(), encoded, "no double encoding");
    let back = encoded.to_linear();
    assert_eq!(back.encoding, Encoding::Linear);
    for (a, b) in back.data.iter().zip(&linear.data) {
        assert!((a - b).abs() < 1e-6);
    }
    assert_eq!(linear.pixel(1, 0), &[0.5, 0.5, 0.5, 0.25]);
}

#[test]
fn exr_float_is_exact_and_half_within_precision() {
    let dir = temp_dir("exr");
    for channels in 1..=4u8 {
        let image = Image::from_fn(23, 9, channels, |x, y, c| {
            (x as f32 - 3.0) * 1.37 + y as f32 * 100.5 + f32::from(c) / 7.0
        });
        let float = dir.join(format!("f{channels}.exr"));
        write_exr(&float, &image, ExrPrecision::Float).unwrap();
        assert_eq!(read(&float).unwrap(), image);

        let half = dir.join(format!("h{channels}.exr"));
        write_exr(&half, &image, ExrPrecision::Half).unwrap();
        let back = read(&half).unwrap();
        assert_eq!(
            (back.width, back.height, back.channels, back.encoding),
            (23, 9, channels, Encoding::Linear)
        );
        for (a, b) in back.data.iter().zip(&image.data) {
            assert!((a - b).abs() <= b.abs() * 2f32.powi(-11) + 1e-7, "{a} vs {b}");
        }
    }
}

#[test]
fn a_band_of_rows_decodes_only_the_blocks_that_hold_it() {
    let dir = temp_dir("exr-rows");
    // ZIP: blocks of 16 scanlines; 70 rows = 4 whole blocks and one of 6.
    let image = Image::from_fn(37, 70, 1, |x, y, _| (x as f32 - 5.5) * 0.25 + y as f32 * 100.0);
    for (precision, tol) in [(ExrPrecision::Float, 0.0f32), (ExrPrecision::Half, 2f32.powi(-11))] {
        let path = dir.join(format!("y-{precision:?}.exr"));
        write_exr(&path, &image, precision).unwrap();
        for (asked, read_rows) in
            [(20..21, 16..32), (15..33, 0..48), (60..99, 48..70), (0..70, 0..70), (80..90, 70..70)]
        {
            let (band, rows) = read_exr_rows(&path, asked.clone()).unwrap();
            assert_eq!(rows, read_rows, "{asked:?}");
            assert_eq!(
                (band.width, band.height, band.channels, band.encoding),
                (37, 70, 1, Encoding::Linear)
            );
            for y in 0..70u32 {
                for x in 0..37u32 {
                    let (got, want) = (band.pixel(x, y)[0], image.pixel(x, y)[0]);
                    if rows.contains(&y) {
                        assert!((got - want).abs() <= want.abs() * tol, "({x}, {y}): {got} vs {want}");
                    } else {
                        assert_eq!(got, 0.0, "({x}, {y}) outside the band");
                    }
                }
            }
        }
    }
    // Three channels: read whole, every row reported read.
    let rgb = ramp(9, 40, 3, 255).with_encoding(Encoding::Linear);
    let path = dir.join("rgb.exr");
    write_exr(&path, &rgb, ExrPrecision::Float).unwrap();
    assert_eq!(read_exr_rows(&path, 3..4).unwrap(), (rgb, 0..40));
    // Not an EXR: read whole.
    let png_image = srgb(ramp(5, 33, 1, 255));
    let png = dir.join("y.png");
    write_png(&png, &png_image, BitDepth::Eight).unwrap();
    assert_eq!(read_rows(&png, 3..4).unwrap(), (png_image, 0..33));
    let (band, rows) = read_rows(dir.join("y-Float.exr"), 20..21).unwrap();
    assert_eq!((rows, band.pixel(3, 20)[0]), (16..32, image.pixel(3, 20)[0]));
    // A damaged file is an error naming it, not a panic or a short band.
    let bytes = std::fs::read(dir.join("y-Float.exr")).unwrap();
    let cut = dir.join("cut.exr");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let err = read_exr_rows(&cut, 60..70).unwrap_err();
    assert_eq!(err.path(), cut, "{err}");
    assert!(read_exr_rows(dir.join("missing.exr"), 0..1).is_err());
    // Bytes flipped anywhere (header, offset table, blocks): an answer or an error, never a
    // panic, and an answer is the image's size.
    let bad = dir.join("flipped.exr");
    for k in (0..bytes.len()).step_by(97) {
        let mut b = bytes.clone();
        b[k] ^= 0x5a;
        std::fs::write(&bad, &b).unwrap();
        if let Ok((band, rows)) = read_exr_rows(&bad, 30..40) {
            assert_eq!(
                band.data.len(),
                band.width as usize * band.height as usize * usize::from(band.channels)
            );
            assert!(rows.end <= band.height, "byte {k}");
        }
    }
}

#[test]
fn exr_refuses_srgb_images() {
    let dir = temp_dir("exr-srgb");
    let image = srgb(Image::new(2, 2, 3));
    assert!(matches!(
        write_exr(dir.join("x.exr"), &image, ExrPrecision::Half),
        Err(IoError::Encoding { .. })
    ));
}

fn maps() -> Vec<Layer> {
    let (w, h) = (13, 8);
    let rgb = |s: f32| Image::from_fn(w, h, 3, move |x, y, c| s * (x + y) as f32 + f32::from(c));
    let names = |n: &[&str]| n.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    vec![
        Layer { name: "diffuse".into(), channels: names(&["R", "G", "B"]), image: rgb(0.1) },
        Layer { name: "specular".into(), channels: names(&["R", "G", "B"]), image: rgb(0.2) },
        Layer {
            name: "roughness".into(),
            channels: names(&["Y"]),
            image: Image::from_fn(w, h, 1, |x, _, _| x as f32 / 13.0),
        },
        Layer {
            name: "normal".into(),
            channels: names(&["X", "Y", "Z"]),
            image: Image::from_fn(w, h, 3, |x, y, c| [x as f32, y as f32, -1.0][c as usize] / 13.0),
        },
        Layer {
            name: "custom".into(),
            channels: names(&["zeta", "alpha"]),
            image: rgb(0.3).to_linear_gray(),
        },
    ]
}

trait Gray {
    fn to_linear_gray(&self) -> Image;
}

impl Gray for Image {
    /// First two channels of an image, to test non-conventional names keep their order.
    fn to_linear_gray(&self) -> Image {
        Image::from_fn(self.width, self.height, 2, |x, y, c| self.get(x, y, c))
    }
}

#[test]
fn multi_layer_exr_round_trip_keeps_names_and_order() {
    let dir = temp_dir("layers");
    let path = dir.join("fit.exr");
    let layers = maps();
    write_exr_layers(&path, &layers, ExrPrecision::Float).unwrap();
    let back = read_exr_layers(&path).unwrap();
    assert_eq!(back, layers);
    // A multi-layer file is not silently flattened by `read`.
    let err = read(&path).unwrap_err();
    assert!(matches!(err, IoError::Unsupported { .. }), "{err}");
    assert!(err.to_string().contains("read_exr_layers"), "{err}");
}

#[test]
fn multi_layer_exr_rejects_mismatched_layers() {
    let dir = temp_dir("layers-bad");
    let mut layers = maps();
    layers[2].image = Image::new(5, 5, 1);
    let err = write_exr_layers(dir.join("bad.exr"), &layers, ExrPrecision::Half).unwrap_err();
    assert!(matches!(err, IoError::SizeMismatch { .. }), "{err}");
    let mut layers = maps();
    layers[0].channels.pop();
    let err = write_exr_layers(dir.join("bad.exr"), &layers, ExrPrecision::Half).unwrap_err();
    assert!(matches!(err, IoError::InvalidImage { .. }), "{err}");
    assert!(!dir.join("bad.exr").exists());
}

#[test]
fn truncated_files_name_the_file() {
    let dir = temp_dir("trunc");
    let image = srgb(ramp(64, 64, 3, 255));
    let png = dir.join("img_000012.png");
    write_png(&png, &image, BitDepth::Eight).unwrap();
    let exr = dir.join("img_000012.exr");
    write_exr(&exr, &image.clone().with_encoding(Encoding::Linear), ExrPrecision::Float).unwrap();
    let tif = dir.join("img_000012.tif");
    write_tiff(&tif, &image, BitDepth::Sixteen).unwrap();
    for path in [png, exr, tif] {
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let err = read(&path).unwrap_err();
        assert!(matches!(err, IoError::Truncated { .. }), "{err:?}");
        assert_eq!(err.path(), path);
        let msg = err.to_string();
        assert!(msg.starts_with(&path.display().to_string()), "{msg}");
        eprintln!("{msg}");
    }
}

#[test]
fn empty_and_tiny_files_are_truncated() {
    let dir = temp_dir("tiny");
    let path = dir.join("empty.png");
    std::fs::write(&path, b"").unwrap();
    assert!(matches!(read(&path), Err(IoError::Truncated { .. })));
    std::fs::write(&path, b"\x89PNG").unwrap();
    assert!(matches!(read(&path), Err(IoError::Truncated { .. })));
}

#[test]
fn stack_with_a_different_size_names_the_file() {
    let dir = temp_dir("stack");
    let a = srgb(ramp(8, 6, 3, 255));
    let paths: Vec<PathBuf> = (0..3).map(|i| dir.join(format!("exp_{i}.png"))).collect();
    write_png(&paths[0], &a, BitDepth::Eight).unwrap();
    write_png(&paths[1], &a, BitDepth::Eight).unwrap();
    write_png(&paths[2], &srgb(ramp(8, 5, 3, 255)), BitDepth::Eight).unwrap();
    assert_eq!(read_stack(&paths[..2]).unwrap(), vec![a.clone(), a.clone()]);
    match read_stack(&paths) {
        Err(e @ IoError::SizeMismatch { .. }) => {
            assert_eq!(e.path(), paths[2]);
            let msg = e.to_string();
            assert!(msg.contains("exp_2.png") && msg.contains("8x5") && msg.contains("8x6"), "{msg}");
        }
        other => panic!("expected SizeMismatch, got {other:?}"),
    }
    // Same size, other bit depth.
    write_png(&paths[2], &a, BitDepth::Sixteen).unwrap();
    match read_stack(&paths) {
        Err(IoError::BitDepth { path, found: 16, expected: 8 }) => assert_eq!(path, paths[2]),
        other => panic!("expected BitDepth, got {other:?}"),
    }
}

#[test]
fn expected_bit_depth_is_enforced() {
    let dir = temp_dir("depth");
    let path = dir.join("eight.png");
    write_png(&path, &srgb(Image::new(2, 2, 1)), BitDepth::Eight).unwrap();
    let opts = ReadOptions { expect_depth: Some(BitDepth::Sixteen), ..ReadOptions::default() };
    let err = read_with(&path, opts).unwrap_err();
    assert!(matches!(err, IoError::BitDepth { found: 8, expected: 16, .. }), "{err}");
    assert!(err.to_string().contains("wrong bit depth"), "{err}");
}

#[test]
fn unsupported_and_missing_files() {
    let dir = temp_dir("unsupported");
    let bmp = dir.join("x.bmp");
    std::fs::write(&bmp, b"BM\x3a\0\0\0\0\0\0\0\x36\0\0\0").unwrap();
    let err = read(&bmp).unwrap_err();
    assert!(matches!(err, IoError::Unsupported { .. }), "{err}");
    assert!(err.to_string().contains("x.bmp"));
    let big = dir.join("big.tif");
    std::fs::write(&big, b"II+\0\x08\0\0\0\x10\0\0\0\0\0\0\0").unwrap();
    assert!(matches!(read(&big), Err(IoError::Unsupported { .. })));
    let lie = dir.join("lie.png");
    std::fs::write(&lie, b"GIF89a\x01\0\x01\0\0\0\0;").unwrap();
    assert!(matches!(read(&lie), Err(IoError::Unsupported { .. })));
    let missing = dir.join("nope.png");
    let err = read(&missing).unwrap_err();
    assert!(matches!(err, IoError::Open { .. }) && err.to_string().contains("nope.png"), "{err}");
    // 2-channel TIFF output is refused with a reason rather than failing inside the encoder.
    let la = srgb(Image::new(2, 2, 2));
    assert!(matches!(write_tiff(dir.join("la.tif"), &la, BitDepth::Eight), Err(IoError::Unsupported { .. })));
}

#[test]
fn inconsistent_images_are_errors_not_panics() {
    let dir = temp_dir("invalid");
    let mut image = srgb(Image::new(4, 4, 3));
    image.data.pop();
    assert!(matches!(
        write_png(dir.join("a.png"), &image, BitDepth::Eight),
        Err(IoError::InvalidImage { .. })
    ));
    image.channels = 7;
    assert!(matches!(
        write_exr(dir.join("a.exr"), &image, ExrPrecision::Half),
        Err(IoError::InvalidImage { .. })
    ));
}

#[test]
fn writes_replace_atomically_and_leave_no_temp_files() {
    let dir = temp_dir("atomic");
    let path = dir.join("out.png");
    write_png(&path, &srgb(Image::new(3, 3, 1)), BitDepth::Eight).unwrap();
    let white = srgb(Image::from_fn(3, 3, 1, |_, _, _| 1.0));
    write_png(&path, &white, BitDepth::Eight).unwrap();
    assert_eq!(read(&path).unwrap(), white);
    let entries: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(entries, vec![std::ffi::OsString::from("out.png")]);
    let nowhere = dir.join("no-such-dir").join("out.png");
    let err = write_png(&nowhere, &white, BitDepth::Eight).unwrap_err();
    assert!(matches!(err, IoError::Open { .. }) && err.path() == nowhere, "{err}");
}

#[test]
fn accessors_index_interleaved_row_major() {
    let image = Image::from_fn(3, 2, 2, |x, y, c| (x * 100 + y * 10 + u32::from(c)) as f32);
    assert_eq!(image.get(2, 1, 1), 211.0);
    assert_eq!(image.pixel(1, 1), &[110.0, 111.0]);
    assert_eq!(image.data[(3 + 2) * 2], 210.0);
}

#[test]
fn single_part_exr_with_dotted_channel_names_splits_into_layers() {
    use exr::prelude::{self as x, WritableImage};
    let dir = temp_dir("dotted");
    let path = dir.join("legacy.exr");
    let (w, h) = (4usize, 3usize);
    let plane = |v: f32| x::FlatSamples::F32((0..w * h).map(|i| v + i as f32).collect());
    let channels = x::AnyChannels::sort(x::SmallVec::from_vec(vec![
        x::AnyChannel::new("diffuse.R", plane(1.0)),
        x::AnyChannel::new("diffuse.G", plane(2.0)),
        x::AnyChannel::new("diffuse.B", plane(3.0)),
        x::AnyChannel::new("depth.Z", plane(9.0)),
    ]));
    x::Image::from_channels((w, h), channels).write().to_file(&path).unwrap();
    let layers = read_exr_layers(&path).unwrap();
    let names: Vec<(&str, Vec<&str>)> =
        layers.iter().map(|l| (l.name.as_str(), l.channels.iter().map(String::as_str).collect())).collect();
    assert_eq!(names, vec![("depth", vec!["Z"]), ("diffuse", vec!["R", "G", "B"])]);
    assert_eq!(layers[1].image.pixel(1, 0), &[2.0, 3.0, 4.0]);
}

#[test]
fn float_tiff_reads_as_linear_raw_values() {
    let dir = temp_dir("ftiff");
    let path = dir.join("float.tif");
    let data: Vec<f32> = (0..2 * 2 * 3).map(|i| i as f32 * 0.75 - 2.0).collect();
    let buffer = image::ImageBuffer::<image::Rgb<f32>, _>::from_raw(2, 2, data.clone()).unwrap();
    image::DynamicImage::ImageRgb32F(buffer).save(&path).unwrap();
    let back = read(&path).unwrap();
    assert_eq!((back.encoding, back.channels, &back.data), (Encoding::Linear, 3, &data));
    let opts = ReadOptions { expect_depth: Some(BitDepth::Sixteen), ..ReadOptions::default() };
    assert!(matches!(read_with(&path, opts), Err(IoError::BitDepth { found: 32, .. })));
}

#[test]
fn corrupted_files_give_errors_not_panics() {
    let dir = temp_dir("corrupt");
    let image = ramp(16, 16, 3, 255);
    let sources = [
        ("a.png", {
            write_png(dir.join("a.png"), &srgb(image.clone()), BitDepth::Sixteen).unwrap();
            std::fs::read(dir.join("a.png")).unwrap()
        }),
        ("a.tif", {
            write_tiff(dir.join("a.tif"), &srgb(image.clone()), BitDepth::Eight).unwrap();
            std::fs::read(dir.join("a.tif")).unwrap()
        }),
        ("a.exr", {
            write_exr(dir.join("a.exr"), &image, ExrPrecision::Half).unwrap();
            std::fs::read(dir.join("a.exr")).unwrap()
        }),
    ];
    // Deterministic xorshift so failures reproduce.
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    for (name, bytes) in &sources {
        let path = dir.join(format!("bad-{name}"));
        for _ in 0..150 {
            let mut bad = bytes.clone();
            for _ in 0..1 + next() % 4 {
                let i = (next() % bad.len() as u64) as usize;
                bad[i] = next() as u8;
            }
            if next() % 3 == 0 {
                bad.truncate((next() % bad.len() as u64) as usize);
            }
            std::fs::write(&path, &bad).unwrap();
            if let Err(e) = read(&path) {
                assert_eq!(e.path(), path);
            }
        }
    }
}

#[test]
fn a_file_decoded_from_its_bytes_is_the_file_read() {
    let dir = temp_dir("decode");
    let wide = srgb(ramp(31, 7, 3, 65535));
    let png = dir.join("f.png");
    write_png(&png, &wide, BitDepth::Sixteen).unwrap();
    let tif = dir.join("f.tif");
    write_tiff(&tif, &srgb(ramp(9, 4, 1, 255)), BitDepth::Eight).unwrap();
    let exr = dir.join("f.exr");
    let linear = Image::from_fn(13, 5, 1, |x, y, _| x as f32 * 0.25 + y as f32);
    write_exr(&exr, &linear, ExrPrecision::Half).unwrap();
    for (path, bits) in [(&png, 16), (&tif, 8), (&exr, 16)] {
        let bytes = std::fs::read(path).unwrap();
        let (image, got_bits) = decode(&bytes, path, ReadOptions::default()).unwrap();
        assert_eq!(image, read(path).unwrap(), "{}", path.display());
        assert_eq!(got_bits, bits, "{}", path.display());
    }
    // Damaged bytes are an error naming the frame, not a panic.
    let bytes = std::fs::read(&exr).unwrap();
    let e = decode(&bytes[..bytes.len() / 2], "cam0/frame-7.exr", ReadOptions::default()).unwrap_err();
    assert!(e.to_string().contains("cam0/frame-7.exr"), "{e}");
    let e = decode(b"P5 2 2 255\n", "x.pgm", ReadOptions::default()).unwrap_err();
    assert!(e.to_string().contains("unrecognised format"), "{e}");
}
