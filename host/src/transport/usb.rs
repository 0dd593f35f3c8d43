//! A controller's USB vendor bulk interface (through nusb, no kernel driver) as a
//! [`Transport`], on the wall clock.

use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use super::Transport;

/// USB vendor id of lightrig controllers (pid.codes open-source VID).
pub const USB_VID: u16 = 0x1209;
/// USB product id of lightrig controllers (to be registered with pid.codes before release).
pub const USB_PID: u16 = 0x4C52;
/// The vendor-class interface carrying the protocol, and its bulk endpoints.
pub const USB_INTERFACE: u8 = 0;
/// Bulk OUT endpoint (host to device).
pub const USB_EP_OUT: u8 = 0x01;
/// Bulk IN endpoint (device to host).
pub const USB_EP_IN: u8 = 0x81;

/// The vendor bulk interface of a controller, through nusb (no kernel driver needed).
pub struct UsbTransport {
    tx: nusb::io::EndpointWrite<nusb::transfer::Bulk>,
    rx: nusb::io::EndpointRead<nusb::transfer::Bulk>,
    name: String,
    epoch: Instant,
}

impl UsbTransport {
    /// Opens the first controller (or the one with `serial`) on the bus.
    pub fn open(serial: Option<&str>) -> io::Result<Self> {
        use nusb::transfer::{Bulk, In, Out};
        use nusb::MaybeFuture;
        let info = usb_devices()?
            .into_iter()
            .find(|d| serial.is_none_or(|s| d.serial_number() == Some(s)))
            .ok_or_else(|| {
                io::Error::new(
                    io::ErrorKind::NotFound,
                    format!(
                        "no lightrig controller on USB (VID {USB_VID:04x}, PID {USB_PID:04x}{}); is it plugged in and \
                         are the udev rules installed (docs/boards)?",
                        serial.map(|s| format!(", serial {s}")).unwrap_or_default()
                    ),
                )
            })?;
        let name = format!(
            "usb {}:{} ({})",
            info.bus_id(),
            info.device_address(),
            info.serial_number().unwrap_or("?")
        );
        let device = info.open().wait().map_err(io::Error::other)?;
        let interface = device.claim_interface(USB_INTERFACE).wait().map_err(io::Error::other)?;
        let tx = interface.endpoint::<Bulk, Out>(USB_EP_OUT).map_err(io::Error::other)?.writer(512);
        let rx = interface.endpoint::<Bulk, In>(USB_EP_IN).map_err(io::Error::other)?.reader(512);
        Ok(Self { tx, rx, name, epoch: Instant::now() })
    }
}

/// The lightrig controllers on the USB bus.
pub fn usb_devices() -> io::Result<Vec<nusb::DeviceInfo>> {
    use nusb::MaybeFuture;
    let all = nusb::list_devices().wait().map_err(io::Error::other)?;
    Ok(all.filter(|d| d.vendor_id() == USB_VID && d.product_id() == USB_PID).collect())
}

impl Transport for UsbTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.tx.write_all(bytes)?;
        // Frames are latency-bound: end the transfer now rather than fill a packet.
        self.tx.flush_end()
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        let wait = Duration::from_micros(deadline.saturating_sub(self.now_us()).max(1));
        self.rx.set_read_timeout(wait);
        match self.rx.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut => Ok(0),
            // A signal (Ctrl-C) cut the wait short: nothing arrived, the port is fine. The
            // client's next turn sees what the signal asked for.
            Err(e) if e.kind() == io::ErrorKind::Interrupted => Ok(0),
            Err(e) => Err(e),
        }
    }

    fn now_us(&self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}
