//! Host–device clock mapping: a least-squares line through round-trip samples, so every event's
//! device tick gets a host time.
//!
//! A sample is one `GetClock` round trip: the host sent at `sent`, got the answer at `got` (µs
//! on the transport's clock), and the device read `tick` somewhere in between; the midpoint is
//! the best guess of when. Round trips much slower than the fastest seen (a retransmission, a
//! busy USB bus) carry a large error and are rejected. The fit is over the most recent
//! samples, so slow drift of the device crystal is followed.

use std::collections::VecDeque;

/// Samples kept for the fit.
const WINDOW: usize = 64;

/// One accepted round trip.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sample {
    host_us: f64,
    tick: u64,
    rtt_us: u64,
}

/// `tick ≈ offset + rate · host_us`, fitted to recent samples.
#[derive(Debug, Clone, Default)]
pub struct ClockMap {
    samples: VecDeque<Sample>,
    min_rtt: Option<u64>,
    /// (offset, rate, residual RMS in ticks).
    fit: Option<(f64, f64, f64)>,
    rejected: u32,
}

impl ClockMap {
    /// Adds a round trip; returns whether it was kept.
    pub fn add(&mut self, sent: u64, got: u64, tick: u64) -> bool {
        let rtt = got.saturating_sub(sent);
        let min = self.min_rtt.map_or(rtt, |m| m.min(rtt));
        self.min_rtt = Some(min);
        // Slower than twice the best round trip (plus 100 µs of scheduling noise): an outlier.
        if rtt > 2 * min + 100 {
            self.rejected += 1;
            return false;
        }
        if self.samples.len() == WINDOW {
            self.samples.pop_front();
        }
        let host_us = sent as f64 + rtt as f64 / 2.0;
        self.samples.push_back(Sample { host_us, tick, rtt_us: rtt });
        self.refit();
        true
    }

    fn refit(&mut self) {
        let n = self.samples.len() as f64;
        if self.samples.is_empty() {
            self.fit = None;
            return;
        }
        // Centre both axes for a well-conditioned fit.
        let (h0, t0) = (self.samples[0].host_us, self.samples[0].tick);
        let pts: Vec<(f64, f64)> =
            self.samples.iter().map(|s| (s.host_us - h0, s.tick as f64 - t0 as f64)).collect();
        let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
        let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
        let sxx: f64 = pts.iter().map(|p| (p.0 - mx) * (p.0 - mx)).sum();
        let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
        // One sample (or all at one instant): assume the nominal rate until more arrive.
        let rate = if sxx > 0.0 { sxy / sxx } else { 1.0 };
        let offset_c = my - rate * mx;
        let rms = (pts.iter().map(|p| (p.1 - (offset_c + rate * p.0)).powi(2)).sum::<f64>() / n).sqrt();
        let offset = t0 as f64 + offset_c - rate * h0;
        self.fit = Some((offset, rate, rms));
    }

    /// Host time (µs) of device tick `tick`, once at least one sample is in.
    pub fn host_us(&self, tick: u64) -> Option<f64> {
        let (offset, rate, _) = self.fit?;
        Some((tick as f64 - offset) / rate)
    }

    /// Device ticks per host µs, as fitted.
    pub fn rate(&self) -> Option<f64> {
        self.fit.map(|f| f.1)
    }

    /// RMS distance of the kept samples from the line, in ticks: how well the mapping holds.
    pub fn residual(&self) -> Option<f64> {
        self.fit.map(|f| f.2)
    }

    /// Samples in the fit, and samples rejected as outliers.
    pub fn counts(&self) -> (usize, u32) {
        (self.samples.len(), self.rejected)
    }

    /// The fastest round trip seen, µs.
    pub fn min_rtt_us(&self) -> Option<u64> {
        self.min_rtt
    }

    /// Round-trip times of the kept samples, µs.
    pub fn rtts(&self) -> impl Iterator<Item = u64> + '_ {
        self.samples.iter().map(|s| s.rtt_us)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_offset_and_drift_and_rejects_slow_round_trips() {
        // Device runs 50 ppm fast, started 12 345 µs before the host clock's zero.
        let truth = |host: f64| 12_345.0 + host * 1.000_05;
        let mut m = ClockMap::default();
        let mut rng = 7u64;
        for k in 0..200u64 {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let jitter = (rng >> 33) % 40; // 0..40 µs of asymmetric delay
            let sent = k * 10_000;
            let rtt = 200 + if k % 17 == 16 { 5_000 } else { jitter }; // every 17th: a retransmission
            let read_at = sent as f64 + 100.0 + (jitter as f64) / 2.0;
            let kept = m.add(sent, sent + rtt, truth(read_at).round() as u64);
            assert_eq!(kept, k % 17 != 16, "sample {k}");
        }
        let rate = m.rate().unwrap();
        assert!((rate - 1.000_05).abs() < 2e-6, "rate {rate}");
        // Mapping a tick back to host time: within the jitter (±20 µs) of the truth.
        let host = 1_950_000.0;
        let err = m.host_us(truth(host).round() as u64).unwrap() - host;
        assert!(err.abs() < 25.0, "error {err} µs");
        assert!(m.residual().unwrap() < 15.0);
        assert_eq!(m.counts().1, 11);
    }
}
