//! Byte transports between the host and a rig controller, each with the clock the link runs
//! on: the wall clock for hardware (serial, USB). The in-process virtual device, on simulated
//! time, is `lightrig_sim::transport::VirtualTransport`.
//!
//! A transport carries frames as bytes; framing, retransmission and ordering are the link's
//! job ([`lightrig_protocol::link`]), so a transport may lose or damage bytes.

use std::io;

mod serial;
mod usb;

pub use serial::{holders, SerialTransport};
pub use usb::{usb_devices, UsbTransport, USB_EP_IN, USB_EP_OUT, USB_INTERFACE, USB_PID, USB_VID};

/// Bytes to and from a device.
pub trait Transport {
    /// Sends `bytes`.
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;

    /// Waits until bytes arrive or the clock reaches `deadline` (µs), whichever is first, and
    /// returns how many were put in `buf` (0 at the deadline).
    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize>;

    /// The transport's clock, µs.
    fn now_us(&self) -> u64;

    /// Where the device is, for messages ("serial /dev/ttyACM0", "virtual rig").
    fn describe(&self) -> String;

    /// Whether the device's time passes while the host is not waiting on [`Transport::recv`]:
    /// every real device, so a host busy elsewhere must keep the link alive
    /// ([`crate::client::Client::busy`]). Not the in-process virtual device, whose time moves
    /// only while the host waits on it.
    fn runs_alone(&self) -> bool {
        true
    }
}

impl<T: Transport + ?Sized> Transport for Box<T> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        (**self).send(bytes)
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        (**self).recv(buf, deadline)
    }

    fn now_us(&self) -> u64 {
        (**self).now_us()
    }

    fn describe(&self) -> String {
        (**self).describe()
    }

    fn runs_alone(&self) -> bool {
        (**self).runs_alone()
    }
}

/// Where to find a device, as written on the command line or in a rig file:
/// `virtual`, `serial:/dev/ttyACM0`, `serial:/dev/ttyUSB0@115200`, `usb`, `usb:SERIAL`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Connect {
    /// The in-process virtual device.
    Virtual,
    /// A serial port at a baud rate.
    Serial { path: String, baud: u32 },
    /// A USB controller, optionally by serial number.
    Usb { serial: Option<String> },
}

impl std::str::FromStr for Connect {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let bad =
            || format!("`{s}`: expected `virtual`, `serial:PATH`, `serial:PATH@BAUD`, `usb` or `usb:SERIAL`");
        match s.split_once(':') {
            None if s == "virtual" => Ok(Connect::Virtual),
            None if s == "usb" => Ok(Connect::Usb { serial: None }),
            Some(("usb", serial)) if !serial.is_empty() => Ok(Connect::Usb { serial: Some(serial.into()) }),
            Some(("serial", rest)) if !rest.is_empty() => {
                let (path, baud) = match rest.rsplit_once('@') {
                    Some((p, b)) => {
                        (p, b.parse().map_err(|_| format!("{}: baud `{b}` is not a number", bad()))?)
                    }
                    None => (rest, 115_200),
                };
                Ok(Connect::Serial { path: path.into(), baud })
            }
            _ => Err(bad()),
        }
    }
}

/// The form [`Connect`] parses: `virtual`, `serial:PATH@BAUD`, `usb`, `usb:SERIAL`.
impl std::fmt::Display for Connect {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Connect::Virtual => f.write_str("virtual"),
            Connect::Serial { path, baud } => write!(f, "serial:{path}@{baud}"),
            Connect::Usb { serial: None } => f.write_str("usb"),
            Connect::Usb { serial: Some(s) } => write!(f, "usb:{s}"),
        }
    }
}

impl Connect {
    /// Opens the transport. The virtual rig is not opened here: it lives in `lightrig-sim`
    /// (`lightrig_sim::transport::open` opens every spec, the virtual one included).
    pub fn open(&self) -> io::Result<Box<dyn Transport>> {
        Ok(match self {
            Connect::Virtual => {
                return Err(io::Error::new(
                    io::ErrorKind::Unsupported,
                    "the virtual rig is opened by lightrig-sim (lightrig_sim::transport::open), not by the host                      library",
                ))
            }
            Connect::Serial { path, baud } => Box::new(SerialTransport::open(path, *baud).map_err(|e| {
                let held: Vec<String> =
                    holders(path).into_iter().map(|(pid, cmd)| format!("pid {pid} (`{cmd}`)")).collect();
                if held.is_empty() {
                    io::Error::other(format!(
                        "serial {path}: {e}; check the path (`lightrig devices`) and permissions (dialout group)"
                    ))
                } else {
                    io::Error::other(format!(
                        "serial {path}: {e}: the port is held by {}; close that program first (a lightrig run \
                         on it is stopped by `lightrig stop`)",
                        held.join(", ")
                    ))
                }
            })?),
            Connect::Usb { serial } => Box::new(UsbTransport::open(serial.as_deref())?),
        })
    }
}

/// A candidate device port.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct Candidate {
    /// How to connect to it.
    pub connect: String,
    /// What the system says it is.
    pub description: String,
}

/// Serial ports and USB controllers attached to this machine.
pub fn candidates() -> Vec<Candidate> {
    let mut out = Vec::new();
    for p in serialport::available_ports().unwrap_or_default() {
        let description = match &p.port_type {
            serialport::SerialPortType::UsbPort(u) => {
                format!("USB serial {:04x}:{:04x} {}", u.vid, u.pid, u.product.clone().unwrap_or_default())
            }
            other => format!("{other:?}"),
        };
        out.push(Candidate { connect: format!("serial:{}", p.port_name), description });
    }
    for d in usb_devices().unwrap_or_default() {
        let serial = d.serial_number().unwrap_or("").to_string();
        out.push(Candidate {
            connect: if serial.is_empty() { "usb".into() } else { format!("usb:{serial}") },
            description: format!("lightrig USB {} {}", d.bus_id(), d.product_string().unwrap_or("")),
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::Connect;

    #[test]
    fn connect_specs_parse_or_say_what_is_expected() {
        assert_eq!("virtual".parse(), Ok(Connect::Virtual));
        assert_eq!("usb".parse(), Ok(Connect::Usb { serial: None }));
        assert_eq!("usb:LR0042".parse(), Ok(Connect::Usb { serial: Some("LR0042".into()) }));
        assert_eq!(
            "serial:/dev/ttyACM0".parse(),
            Ok(Connect::Serial { path: "/dev/ttyACM0".into(), baud: 115_200 })
        );
        assert_eq!(
            "serial:/dev/ttyUSB1@921600".parse(),
            Ok(Connect::Serial { path: "/dev/ttyUSB1".into(), baud: 921_600 })
        );
        let e = "tcp:1.2.3.4".parse::<Connect>().unwrap_err();
        assert!(e.contains("expected `virtual`, `serial:PATH`"), "{e}");
        assert!("serial:/dev/x@fast".parse::<Connect>().unwrap_err().contains("baud `fast`"));
    }

    #[test]
    fn connect_specs_print_as_they_parse() {
        for s in ["virtual", "usb", "usb:LR0042", "serial:/dev/ttyUSB1@921600"] {
            assert_eq!(s.parse::<Connect>().unwrap().to_string(), s);
        }
        assert_eq!(
            "serial:/dev/ttyACM0".parse::<Connect>().unwrap().to_string(),
            "serial:/dev/ttyACM0@115200"
        );
    }
}
