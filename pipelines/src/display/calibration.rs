//! A display's calibration, as the file `lightrig fit display` writes and the planner reads:
//! each axis' coil, frequencies and measured response `|H(f)|`, the still beam's own spread,
//! and what the camera saw of earlier targets (the closed loop: `asked → shown` per axis,
//! inverted when the next target is solved).

use serde::{Deserialize, Serialize};

use super::liquid::Liquid;
use super::mapping::{Axis, Response};

/// The calibration file's format version.
pub const FORMAT: u32 = 1;

/// One axis' coil and what was measured of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AxisCalibration {
    /// The coil's name in the rig file.
    pub coil: String,
    /// Its voice-coil channel.
    pub channel: u8,
    /// Its drive limit (the rig file's `max_amplitude`).
    pub max_drive: f64,
    /// The partials' frequencies, Hz (the response is measured at each).
    pub frequencies_hz: Vec<f64>,
    /// `|H(f)|` at each frequency, m of surface amplitude per full-scale drive.
    pub response_m: Vec<f64>,
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
    /// Angle one screen pixel spans, rad.
    pub pitch_rad: f64,
    /// The still beam's reflection-angle variance on x and y, rad².
    pub beam_var: [f64; 2],
    /// The x and y axes.
    pub axes: [AxisCalibration; 2],
}

impl AxisCalibration {
    /// The axis for the solver, named `name`.
    pub fn axis(&self, name: &'static str) -> Axis {
        let mut points: Vec<(f64, f64)> =
            self.frequencies_hz.iter().copied().zip(self.response_m.iter().copied()).collect();
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
        Axis {
            name,
            frequencies: self.frequencies_hz.clone(),
            response: Response { points },
            max_drive: self.max_drive,
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
            seen: Vec::new(),
        }
    }

    #[test]
    fn the_response_is_sorted_for_the_solver() {
        let a = axis().axis("x");
        assert_eq!(a.response.points, vec![(100.0, 1e-4), (200.0, 2e-4)]);
        assert_eq!(a.frequencies, vec![200.0, 100.0]);
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
            pitch_rad: 0.0125,
            beam_var: [1e-4, 1e-4],
            axes: [axis(), axis()],
        };
        let text = serde_json::to_string(&c).unwrap();
        assert_eq!(serde_json::from_str::<Calibration>(&text).unwrap(), c);
        assert!(c.liquid().is_ok());
    }
}
