//! A bispectral EXR written by another tool (the OpenEXR Python bindings, channels named as the
//! layout's SEXR library names them: `tests/data/make_fichet2021.py`) reads back as the matrix
//! that tool wrote; colour-science's `read_spectral_image_Fichet2021` reads the same file as
//! bispectral.

use lightrig_imaging::io::{BispectralImage, Nm};

#[test]
fn a_fichet_layout_file_written_by_openexr_python_reads_back_exactly() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/fichet2021-bispectral.exr");
    let img = BispectralImage::read(&path).unwrap();
    assert_eq!((img.width, img.height), (4, 3));
    let value = |k: usize, x: usize, y: usize| (0.001 * (1 + k) as f64 * (1 + x + 4 * y) as f64) as f32;
    let diagonal = [400.0, 420.0, 440.5];
    let reradiation = [(400.0, 440.5), (400.0, 520.0), (420.0, 520.0)];
    assert_eq!(img.diagonal.keys().map(|n| n.0).collect::<Vec<_>>(), diagonal);
    assert_eq!(img.reradiation.keys().map(|(i, o)| (i.0, o.0)).collect::<Vec<_>>(), reradiation);
    for (k, nm) in diagonal.iter().enumerate() {
        let v = &img.diagonal[&Nm(*nm)];
        for y in 0..3 {
            for x in 0..4 {
                assert_eq!(v[y * 4 + x], value(k, x, y), "T.{nm}nm at ({x}, {y})");
            }
        }
    }
    for (j, (i, o)) in reradiation.iter().enumerate() {
        let v = &img.reradiation[&(Nm(*i), Nm(*o))];
        for y in 0..3 {
            for x in 0..4 {
                assert_eq!(v[y * 4 + x], value(3 + j, x, y), "T.{i}nm.{o}nm at ({x}, {y})");
            }
        }
    }
    // Written again by us, it reads back the same.
    let out = std::env::temp_dir().join(format!("lightrig-fichet-{}.exr", std::process::id()));
    img.write(&out).unwrap();
    assert_eq!(BispectralImage::read(&out).unwrap(), img);
    std::fs::remove_file(&out).ok();
}

#[test]
fn an_emissive_or_plain_rgb_file_is_refused_with_what_it_holds() {
    let dir = std::env::temp_dir();
    let rgb = dir.join(format!("lightrig-rgb-{}.exr", std::process::id()));
    let img = lightrig_imaging::io::Image {
        width: 2,
        height: 1,
        channels: 3,
        data: vec![0.5; 6],
        encoding: lightrig_imaging::io::Encoding::Linear,
    };
    lightrig_imaging::io::write_exr(&rgb, &img, lightrig_imaging::io::ExrPrecision::Float).unwrap();
    let e = BispectralImage::read(&rgb).unwrap_err().to_string();
    assert!(e.contains("no `T.` channels"), "{e}");
    std::fs::remove_file(&rgb).ok();
}
