//! A display's calibration, as the file `lightrig fit display` writes and the planner reads:
//! each axis' coil, frequencies and measured response `|H(f)|`, the screen, the still beam's
//! own spread,
//! and what the camera saw of earlier targets (the closed loop: `asked → shown` per axis,
//! inverted when the next target is solved).

use serde::{Deserialize, Serialize};

use super::liquid::Liquid;
use super::mapping::{Axis, Response};
use super::screen::Screen;

/// The calibration file's format version.
pub const FORMAT: u32 = 2;

/// One axis' coil and what was measured of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AxisCalibration {
    /// The coil's name in the rig file.
    pub coil: String,
    /// Its voice-coil channel.
    pub channel: u8,
    /// Its drive limit (the rig file's `max_amplitude`).
    pub max_drive: f64,
    /// The frequencies the response was measured at, Hz (the calibration's sweep).
    pub frequencies_hz: Vec<f64>,
    /// `|H(f)|` at each frequency, m of surface amplitude per full-scale drive.
    pub response_m: Vec<f64>,
    /// The frequencies the display plays on this coil, Hz (its partials; `|H|` is
    /// interpolated there).
    pub partials_hz: Vec<f64>,
    /// Earlier targets on this axis: `(α asked of the solver, α the camera saw)`, by `asked`.
    #[serde(default)]
    pub seen: Vec<(f64, f64)>,
}

/// A display's calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// [`FORMAT`].
    pub format: u32,
    /// The liquid preset (`water`, `galinstan`).
    pub liquid: String,
    /// The calibration's drive per partial, fraction of full scale.
    pub drive: f64,
    /// The screen the camera saw.
    pub screen: Screen,
    /// The still beam's facet-tilt variance on x and y (what a still surface's picture holds:
    /// subtracted from a sine's).
    pub beam_var: [f64; 2],
    /// The still beam's spot on the camera's picture, standard deviation in pixels on x and y
    /// (the blur the Ward fit applies to its lobe).
    pub beam_px: [f64; 2],
    /// The x and y axes.
    pub axes: [AxisCalibration; 2],
}

impl AxisCalibration {
    /// The axis for the solver, named `name`, its total slope's standard deviation bounded by
    /// `max_slope` rad (`mapping::LINEAR_LIMIT` unless the rig file says).
    pub fn axis(&self, name: &'static str, max_slope: f64) -> Axis {
        let mut points: Vec<(f64, f64)> =
            self.frequencies_hz.iter().copied().zip(self.response_m.iter().copied()).collect();
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
        Axis {
            name,
            frequencies: self.partials_hz.clone(),
            response: Response { points },
            max_drive: self.max_drive,
            max_slope,
        }
    }

    /// The α to ask of the solver so that the camera sees `target`: the inverse of the earlier
    /// `asked → shown` pairs, linear between them and by the nearest pair's ratio beyond; `target`
    /// itself when nothing was seen yet.
    pub fn asked_for(&self, target: f64) -> f64 {
        let s = &self.seen;
        match s.len() {
            0 => target,
            1 => target * s[0].0 / s[0].1,
            _ => {
                let i = s.partition_point(|&(_, shown)| shown < target).clamp(1, s.len() - 1);
                let ((a0, s0), (a1, s1)) = (s[i - 1], s[i]);
                if target < s0 {
                    target * a0 / s0
                } else if target > s1 {
                    target * a1 / s1
                } else if s1 > s0 {
                    a0 + (a1 - a0) * (target - s0) / (s1 - s0)
                } else {
                    target * a0 / s0
                }
            }
        }
    }

    /// Adds what the camera saw for an asked α (replacing an earlier pair at the same α).
    pub fn saw(&mut self, asked: f64, shown: f64) {
        self.seen.retain(|&(a, _)| (a - asked).abs() > 1e-9 * asked.max(1e-12));
        self.seen.push((asked, shown));
        self.seen.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
}

impl Calibration {
    /// Reads a calibration file's text: a file of another format says so and what to do.
    pub fn from_json(text: &str) -> Result<Calibration, String> {
        let value: serde_json::Value =
            serde_json::from_str(text).map_err(|e| format!("not a display calibration: {e}"))?;
        match value.get("format").and_then(serde_json::Value::as_u64) {
            Some(f) if f == u64::from(FORMAT) => {}
            Some(f) => {
                return Err(format!(
                    "a display calibration of format {f}, this lightrig reads format {FORMAT}: fit \
                     the calibration session again (`lightrig fit display SESSION --out DIR`)"
                ))
            }
            None => return Err("not a display calibration: no `format`".into()),
        }
        serde_json::from_value(value).map_err(|e| format!("not a display calibration: {e}"))
    }

    /// The liquid, or a message naming the unknown preset.
    pub fn liquid(&self) -> Result<Liquid, String> {
        Liquid::preset(&self.liquid)
            .ok_or_else(|| format!("liquid `{}`: known are water, galinstan", self.liquid))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn axis() -> AxisCalibration {
        AxisCalibration {
            coil: "c".into(),
            channel: 0,
            max_drive: 0.5,
            frequencies_hz: vec![200.0, 100.0],
            response_m: vec![2e-4, 1e-4],
            partials_hz: vec![150.0],
            seen: Vec::new(),
        }
    }

    #[test]
    fn the_response_is_sorted_for_the_solver() {
        let a = axis().axis("x", 0.1);
        assert_eq!(a.max_slope, 0.1);
        assert_eq!(a.response.points, vec![(100.0, 1e-4), (200.0, 2e-4)]);
        assert_eq!(a.frequencies, vec![150.0], "the display's partials");
        assert!((a.response.at(150.0).unwrap() - 1.5e-4).abs() < 1e-18);
    }

    #[test]
    fn what_the_camera_saw_is_inverted_for_the_next_target() {
        let mut a = axis();
        assert_eq!(a.asked_for(0.1), 0.1, "nothing seen: ask for the target");
        a.saw(0.10, 0.095);
        assert!((a.asked_for(0.1) - 0.1 * 0.10 / 0.095).abs() < 1e-15);
        a.saw(0.02, 0.02);
        a.saw(0.14, 0.126);
        // Between two seen pairs: linear in shown.
        let ask = a.asked_for(0.11);
        assert!((ask - (0.10 + 0.04 * (0.11 - 0.095) / (0.126 - 0.095))).abs() < 1e-12, "{ask}");
        // Beyond: the nearest pair's ratio.
        assert!((a.asked_for(0.01) - 0.01).abs() < 1e-15);
        assert!((a.asked_for(0.15) - 0.15 * 0.14 / 0.126).abs() < 1e-12);
        // Seeing the same α again replaces it.
        a.saw(0.14, 0.14);
        assert_eq!(a.seen.len(), 3);
        assert!((a.asked_for(0.14) - 0.14).abs() < 1e-12);
    }

    #[test]
    fn the_file_round_trips() {
        let c = Calibration {
            format: FORMAT,
            liquid: "water".into(),
            drive: 0.03,
            screen: Screen {
                distance_m: 0.05,
                pitch_m: 6e-4,
                incidence_rad: 0.0,
                tilt_rad: 0.0,
                centre_px: [96.0, 96.0],
            },
            beam_var: [1e-4, 1e-4],
            beam_px: [1.5, 1.5],
            axes: [axis(), axis()],
        };
        let text = serde_json::to_string(&c).unwrap();
        assert_eq!(Calibration::from_json(&text).unwrap(), c);
        assert!(c.liquid().is_ok());
        // A file of format 1 (before the screen and the sweep) says what to do.
        let old = text.replace("\"format\":2", "\"format\":1");
        let e = Calibration::from_json(&old).unwrap_err();
        assert!(
            e.contains("format 1, this lightrig reads format 2") && e.contains("lightrig fit display"),
            "{e}"
        );
    }
}
