//! The LLS demo's map figures: for each map the scene's truth, the fit and their error side by
//! side (`fit/compare-MAP.png`), masked outside the fitted sample, each scalar panel with its
//! colour bar. The report names the panels and gives the bars' ranges.

use std::path::Path;

use lightrig_host::fit::lls::LlsMaps;
use lightrig_imaging::figure::{row, Panel};
use lightrig_imaging::io::{write_png, BitDepth};
use lightrig_pipelines::vec3::angle;
use lightrig_sim::scenes::lls::{LlsScene, Region};

use crate::error::{failure, CliError};

/// One figure as the report shows it.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// The PNG, relative to the demo's output directory.
    pub file: String,
    /// What the panels show and the colour bars' ranges.
    pub caption: String,
}

/// Writes `out/fit/compare-*.png` for diffuse, specular, roughness, height, normal and (where
/// measured) translucency; returns them in that order.
pub fn write_map_figures(scene: &LlsScene, m: &LlsMaps, out: &Path) -> Result<Vec<Figure>, CliError> {
    let (w, h) = (m.width, m.height);
    let n = (w * h) as usize;
    let zoom = (240 / w).max(1);
    let sample = |i: usize| scene.truth[i].region == Region::Sample;
    let compared = |i: usize| sample(i) && m.fitted[i];
    let truth_rgb = |f: &dyn Fn(usize) -> [f64; 3]| -> Vec<Option<[f32; 3]>> {
        (0..n).map(|i| sample(i).then(|| f(i).map(|v| v as f32))).collect()
    };
    let fit_rgb = |f: &dyn Fn(usize) -> [f64; 3]| -> Vec<Option<[f32; 3]>> {
        (0..n).map(|i| compared(i).then(|| f(i).map(|v| v as f32))).collect()
    };
    let truth_scalar = |f: &dyn Fn(usize) -> f64| -> Vec<Option<f32>> {
        (0..n).map(|i| sample(i).then(|| f(i) as f32)).collect()
    };
    let fit_scalar = |f: &dyn Fn(usize) -> f64| -> Vec<Option<f32>> {
        (0..n).map(|i| compared(i).then(|| f(i) as f32)).collect()
    };
    let mean3 = |a: [f64; 3]| (a[0] + a[1] + a[2]) / 3.0;
    let t = &scene.truth;
    let mut figures = Vec::new();
    let mut write = |name: &str, panels: Vec<Panel>, caption: String| -> Result<(), CliError> {
        let file = format!("fit/compare-{name}.png");
        write_png(out.join(&file), &row(&panels, zoom), BitDepth::Eight).map_err(failure)?;
        figures.push(Figure { file, caption });
        Ok(())
    };

    let e = 0.05;
    write(
        "diffuse",
        vec![
            Panel::colour(w, h, &truth_rgb(&|i| t[i].material.diffuse), 1.0),
            Panel::colour(w, h, &fit_rgb(&|i| m.fit[i].diffuse), 1.0),
            Panel::scalar(
                w,
                h,
                &fit_scalar(&|i| {
                    mean3(std::array::from_fn(|c| (m.fit[i].diffuse[c] - t[i].material.diffuse[c]).abs()))
                }),
                (0.0, e),
            ),
        ],
        format!("diffuse ρd: truth | fit | mean |error| over R, G, B (colour bar 0 – {e})"),
    )?;
    let (gain, e) = (5.0, 0.2);
    write(
        "specular",
        vec![
            Panel::colour(w, h, &truth_rgb(&|i| t[i].material.specular), gain),
            Panel::colour(w, h, &fit_rgb(&|i| m.fit[i].specular), gain),
            Panel::scalar(
                w,
                h,
                &fit_scalar(&|i| {
                    mean3(std::array::from_fn(|c| {
                        (m.fit[i].specular[c] / t[i].material.specular[c] - 1.0).abs()
                    }))
                }),
                (0.0, e),
            ),
        ],
        format!("specular ρs: truth | fit (both × {gain}) | mean relative |error| (colour bar 0 – {e})"),
    )?;
    let (range, e) = ((0.0, 0.32), 0.2);
    write(
        "roughness",
        vec![
            Panel::scalar(w, h, &truth_scalar(&|i| t[i].material.alpha), range),
            Panel::scalar(w, h, &fit_scalar(&|i| m.fit[i].alpha), range),
            Panel::scalar(
                w,
                h,
                &fit_scalar(&|i| (m.fit[i].alpha / t[i].material.alpha - 1.0).abs()),
                (0.0, e),
            ),
        ],
        format!(
            "Ward α: truth | fit (colour bars {} – {}) | relative |error| (colour bar 0 – {e})",
            range.0, range.1
        ),
    )?;
    if m.measured.height {
        let heights: Vec<f64> = (0..n).filter(|&i| sample(i)).map(|i| t[i].point[2]).collect();
        let lo = heights.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = heights.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let e = 0.5;
        let z = |i: usize| m.points[i].map_or(f64::NAN, |p| p[2]);
        write(
            "height",
            vec![
                Panel::scalar(w, h, &truth_scalar(&|i| t[i].point[2]), (lo as f32, hi as f32)),
                Panel::scalar(w, h, &fit_scalar(&z), (lo as f32, hi as f32)),
                Panel::scalar(w, h, &fit_scalar(&|i| (z(i) - t[i].point[2]).abs()), (0.0, e)),
            ],
            format!(
                "height: truth | fit (colour bars {lo:.2} – {hi:.2} mm) | |error| (colour bar 0 – {e} mm)"
            ),
        )?;
    }
    if m.measured.normals {
        let rgb = |v: [f64; 3]| v.map(|x| (x + 1.0) / 2.0);
        let e = 5.0;
        let normal = |i: usize| m.normals[i].unwrap_or([f64::NAN; 3]);
        write(
            "normal",
            vec![
                Panel::colour(w, h, &truth_rgb(&|i| rgb(t[i].normal)), 1.0),
                Panel::colour(w, h, &fit_rgb(&|i| rgb(normal(i))), 1.0),
                Panel::scalar(w, h, &fit_scalar(&|i| angle(normal(i), t[i].normal).to_degrees()), (0.0, e)),
            ],
            format!("normal (x, y, z as (n + 1)/2 in R, G, B): truth | fit | angle between them (colour bar 0 – {e}°)"),
        )?;
    }
    if m.measured.translucency {
        let hi = (0..n).filter(|&i| sample(i)).map(|i| t[i].translucency).fold(0.0, f64::max).max(1e-6);
        let e = 0.05;
        let fitted = |i: usize| f64::from(m.translucency[i]);
        write(
            "translucency",
            vec![
                Panel::scalar(w, h, &truth_scalar(&|i| t[i].translucency), (0.0, hi as f32)),
                Panel::scalar(w, h, &fit_scalar(&fitted), (0.0, hi as f32)),
                Panel::scalar(w, h, &fit_scalar(&|i| (fitted(i) - t[i].translucency).abs()), (0.0, e)),
            ],
            format!("translucency: truth | fit (colour bars 0 – {hi:.3}) | |error| (colour bar 0 – {e})"),
        )?;
    }
    Ok(figures)
}
