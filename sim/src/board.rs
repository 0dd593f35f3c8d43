//! The simulated board a rig file describes: switches where the axes' homing expects them and
//! with the file's polarities, interlocks closed, cameras answering their triggers with
//! exposure edges.

use lightrig_firmware::sim::{SimBoard, SimExposure};
use lightrig_host::rigfile::RigFile;
use lightrig_protocol::config::{HomingMode, Input, Polarity};

fn wired_low(i: Input) -> bool {
    i == Input::Wired(Polarity::ActiveLow)
}

/// The simulated board a rig file describes. Physical and logical positions agree once an
/// axis is homed: the homing switch sits where the homing procedure (switch, back-off, call it
/// `position`) puts the file's `position`.
pub fn board_for(rig: &RigFile) -> SimBoard {
    let mut board = SimBoard { record_steps: false, ..SimBoard::default() };
    for s in &rig.steppers {
        let Some(m) = board.steppers.get_mut(usize::from(s.axis)) else { continue };
        m.active_low = [wired_low(s.limit_min), wired_low(s.limit_max), wired_low(s.index)];
        let at = |units: f64| s.steps(units).unwrap_or(0);
        let (p, b) = (s.homing.position, s.homing.backoff);
        match s.homing.mode {
            HomingMode::ToMinLimit => m.limit_min_at = Some(at(p - b)),
            HomingMode::ToMaxLimit => m.limit_max_at = Some(at(p + b)),
            HomingMode::ToIndex => {
                let rev = at(360.0).max(1);
                m.index_at = Some((at(p).rem_euclid(rev), rev));
            }
            HomingMode::None => {}
        }
        // Limit switches not used for homing sit just beyond the soft limits.
        if let Some((lo, hi)) = s.limits {
            if m.limit_min_at.is_none() && s.limit_min != Input::Unused {
                m.limit_min_at = Some(at(lo) - at(2.0).abs().max(1));
            }
            if m.limit_max_at.is_none() && s.limit_max != Input::Unused {
                m.limit_max_at = Some(at(hi) + at(2.0).abs().max(1));
            }
        }
    }
    for w in &rig.filter_wheels {
        if let Some(m) = board.wheels.get_mut(usize::from(w.wheel)) {
            m.active_low[2] = wired_low(w.index);
            m.index_at = Some((0, i64::from(w.steps_per_rev.max(1))));
        }
    }
    for l in &rig.lasers {
        if let (Some(level), Input::Wired(p)) =
            (board.interlocks.get_mut(usize::from(l.channel)), l.interlock)
        {
            // Closed: the level the device reads as "safe".
            *level = p == Polarity::ActiveHigh;
        }
    }
    for c in &rig.cameras {
        if let Some(e) = board.exposure.get_mut(usize::from(c.camera)) {
            if let Input::Wired(p) = c.exposure_input {
                *e = Some(SimExposure {
                    delay: 0,
                    length: c.pulse_us.round().max(1.0) as u64,
                    trigger_active_low: c.polarity == Polarity::ActiveLow,
                    output_active_low: p == Polarity::ActiveLow,
                });
            }
        }
    }
    board
}
