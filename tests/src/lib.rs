//! Shared pieces of the cross-crate tests in `tests/tests/`.
//!
//! [`Pair`] joins a host link to a firmware [`Controller`] by a perfect wire under simulated
//! time, so a test can inject its own bytes and inspect both ends.

use lightrig_firmware::sim::SimBoard;
use lightrig_firmware::sim::{virtual_device_info, SimClock};
use lightrig_firmware::Controller;
use lightrig_protocol::link::{Delivery, Link, LinkConfig, Role};
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::{Command, DeviceMsg, HostMsg, MAX_FRAME};

/// Host link, device controller and a perfect wire.
pub struct Pair {
    /// Simulated device time (1 tick = 1 µs).
    pub clock: SimClock,
    /// The host end.
    pub host: Link<HostMsg, DeviceMsg, 8>,
    /// The device.
    pub device: Controller<SimClock, SimBoard>,
}

/// Retransmission timeout used by both ends, in ticks.
pub const RTO: u64 = 1_000;

impl Pair {
    /// A fresh pair; the host has started connecting.
    pub fn new() -> Self {
        let clock = SimClock::default();
        let device = Controller::new(clock.clone(), SimBoard::default(), virtual_device_info(), RTO);
        let mut host = Link::new(Role::Initiator, LinkConfig { rto: RTO, rx_reserve: 0, nonce: 0x1157 });
        host.connect(0);
        Self { clock, host, device }
    }

    /// The device restarts (power cycle): a new controller with a new boot id, same clock.
    pub fn restart_device(&mut self) {
        let boot_id = self.device.info().boot_id.wrapping_add(1);
        let info = DeviceInfo { boot_id, ..virtual_device_info() };
        self.device = Controller::new(self.clock.clone(), SimBoard::default(), info, RTO);
    }

    /// Moves frames both ways for `ticks` ticks; returns what the host received.
    pub fn run(&mut self, ticks: u64) -> Vec<Delivery<DeviceMsg>> {
        let mut got = Vec::new();
        let mut out = [0u8; MAX_FRAME];
        for _ in 0..ticks {
            let now = lightrig_firmware::Clock::now(&self.clock);
            while let Some(n) = self.host.poll_transmit(now, &mut out) {
                self.device.receive(&out[..n]);
            }
            self.device.poll();
            while let Some(n) = self.device.poll_transmit(&mut out) {
                self.host.receive_all(&out[..n], now, |d| got.push(d));
            }
            self.clock.advance(1);
        }
        got
    }

    /// Sends a request and returns every message the host got within `ticks`.
    pub fn request(&mut self, id: u16, command: Command, ticks: u64) -> Vec<DeviceMsg> {
        self.host.send(HostMsg { id, command }).expect("window");
        self.messages(ticks)
    }

    /// Runs the wire and keeps only messages.
    pub fn messages(&mut self, ticks: u64) -> Vec<DeviceMsg> {
        self.run(ticks)
            .into_iter()
            .filter_map(|d| match d {
                Delivery::Message(m) => Some(m),
                _ => None,
            })
            .collect()
    }
}

impl Default for Pair {
    fn default() -> Self {
        Self::new()
    }
}
