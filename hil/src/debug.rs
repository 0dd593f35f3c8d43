//! The emulated board's debug port (UART1): what its pins did, from the recorder
//! (`lightrig_firmware::record`).

use lightrig_firmware::record::{request, Answer, Output, Record, RECORDS_PER_READ, RECORD_LEN};
use lightrig_host::transport::{SerialTransport, Transport};
use lightrig_protocol::frame::FrameDecoder;
use lightrig_protocol::{MAX_FRAME, MAX_PACKET};

/// The recorder, over its serial port.
pub struct DebugPort {
    port: SerialTransport,
    decoder: FrameDecoder,
    /// Number of the next record not yet read.
    pub cursor: u64,
}

/// The board's counters, from the info answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardInfo {
    /// Records written since start.
    pub written: u64,
    /// The board's tick.
    pub now: u64,
    /// Protocol UART bytes received.
    pub rx_bytes: u64,
    /// Protocol UART bytes sent.
    pub tx_bytes: u64,
    /// Cycles (25 MHz) the run loop spent working, not waiting.
    pub busy_cycles: u64,
    /// Run-loop turns.
    pub wakeups: u64,
}

impl DebugPort {
    /// Opens the debug port at `path`.
    pub fn open(path: &str) -> Result<Self, String> {
        let port = SerialTransport::open(path, 115_200).map_err(|e| format!("debug port {path}: {e}"))?;
        Ok(Self { port, decoder: FrameDecoder::new(), cursor: 0 })
    }

    /// Sends one request and returns the answer packet (up to 3 tries of 2 s).
    fn ask(&mut self, req: &[u8]) -> Result<Vec<u8>, String> {
        let mut buf = [0u8; MAX_PACKET];
        buf[..req.len()].copy_from_slice(req);
        let mut frame = [0u8; MAX_FRAME];
        let n = lightrig_protocol::frame::seal(&mut buf, req.len(), &mut frame);
        for _ in 0..3 {
            self.decoder.reset();
            self.port.send(&frame[..n]).map_err(|e| format!("debug port: {e}"))?;
            let deadline = self.port.now_us() + 2_000_000;
            let mut rx = [0u8; 1024];
            while self.port.now_us() < deadline {
                let got = self.port.recv(&mut rx, deadline).map_err(|e| format!("debug port: {e}"))?;
                let mut answer = None;
                self.decoder.feed(&rx[..got], |p| {
                    if let Ok(p) = p {
                        answer = Some(p.to_vec());
                    }
                });
                if let Some(a) = answer {
                    return Ok(a);
                }
            }
        }
        Err("the debug port does not answer".into())
    }

    /// Reads the board's counters.
    pub fn info(&mut self) -> Result<BoardInfo, String> {
        let p = self.ask(&request::info())?;
        match Answer::decode(&p) {
            Some(Answer::Info { written, now, counters: [rx, tx, busy, wakeups], .. }) => {
                Ok(BoardInfo { written, now, rx_bytes: rx, tx_bytes: tx, busy_cycles: busy, wakeups })
            }
            other => Err(format!("unexpected debug answer {other:?}")),
        }
    }

    /// Skips everything recorded so far: later reads start at the next change.
    pub fn mark(&mut self) -> Result<(), String> {
        self.cursor = self.info()?.written;
        Ok(())
    }

    /// Moves the cursor back to the oldest record the ring still holds.
    pub fn rewind(&mut self) -> Result<(), String> {
        let p = self.ask(&request::read(0, 0))?;
        match Answer::decode(&p) {
            Some(Answer::Records { first, .. }) => {
                self.cursor = first;
                Ok(())
            }
            other => Err(format!("unexpected debug answer {other:?}")),
        }
    }

    /// Opens or closes a laser's interlock input.
    pub fn set_interlock(&mut self, channel: u8, closed: bool) -> Result<(), String> {
        let p = self.ask(&request::set_interlock(channel, closed))?;
        match Answer::decode(&p) {
            Some(Answer::InterlockSet) => Ok(()),
            other => Err(format!("unexpected debug answer {other:?}")),
        }
    }

    /// Every record from the cursor to the newest; an error if the ring overwrote some first.
    pub fn read_new(&mut self) -> Result<Vec<Record>, String> {
        let mut out = Vec::new();
        loop {
            let p = self.ask(&request::read(self.cursor, RECORDS_PER_READ as u8))?;
            let Some(Answer::Records { first, written, records }) = Answer::decode(&p) else {
                return Err("unexpected debug answer to a read".into());
            };
            if first != self.cursor {
                return Err(format!(
                    "recorder overwrote records {}..{first} before they were read",
                    self.cursor
                ));
            }
            for r in records.chunks(RECORD_LEN) {
                out.push(Record::decode(r).ok_or("undecodable record")?);
            }
            self.cursor = first + (records.len() / RECORD_LEN) as u64;
            if self.cursor >= written {
                return Ok(out);
            }
        }
    }
}

/// The changes of one kind among `records`, as `(tick, output)`.
pub fn only(records: &[Record], keep: impl Fn(&Output) -> bool) -> Vec<(u64, Output)> {
    records.iter().filter(|r| keep(&r.output)).map(|r| (r.tick, r.output)).collect()
}
