//! Firmware images and their transfer over the rig's link (`lightrig flash`).
//!
//! An image file (`.lrfw`) is the signed bytes (the firmware's code, `0xFF` padding to a
//! multiple of 64 bytes, the 64-byte trailer naming board, version, schema hash and code
//! length: [`lightrig_protocol::update`]) followed by the 64-byte ed25519 signature of their
//! SHA-512, as embassy-boot verifies it. Keys are 32 bytes written as 64 hex digits: the
//! secret (`lightrig flash keygen`'s `NAME.key`, never shared) and the public key (`NAME.pub`,
//! built into the firmware).
//!
//! [`send`] carries an image to a device: `Begin` (the device refuses an image for another
//! board before anything is written), the chunks from where the device stands (a transfer cut
//! by an unplug goes on where it stopped), `Finish`; the device then resets into the
//! bootloader, which swaps the image in. [`confirm`] keeps it once the new firmware answers.

use std::path::Path;

use ed25519_dalek::{Signer, SigningKey, Verifier, VerifyingKey};
use heapless::Vec as HVec;
use lightrig_protocol::session::{BoardId, Version};
use lightrig_protocol::update::UPDATE_CHUNK;
use lightrig_protocol::update::{
    ImageInfo, Signature, UpdateCommand, UpdatePhase, UpdateStatus, TRAILER_LEN,
};
use lightrig_protocol::{Command, Reply};
use sha2::{Digest, Sha512};

use crate::client::{Client, ClientError};
use crate::transport::Transport;

/// A signed firmware image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image {
    /// What its trailer says.
    pub info: ImageInfo,
    /// Code, padding and trailer: what the device stores.
    pub signed: Vec<u8>,
    /// ed25519 over the SHA-512 of `signed`.
    pub signature: [u8; 64],
}

/// The SHA-512 that is signed.
fn digest(bytes: &[u8]) -> [u8; 64] {
    Sha512::digest(bytes).into()
}

impl Image {
    /// Code, padding and trailer for `info` (its `code_len` is set from `code`).
    pub fn signed_bytes(
        code: &[u8],
        board: BoardId,
        version: Version,
        schema_hash: u64,
    ) -> (ImageInfo, Vec<u8>) {
        let info = ImageInfo { board, version, schema_hash, code_len: code.len() as u32 };
        let mut out = code.to_vec();
        out.resize(info.trailer_at() as usize, 0xFF);
        out.extend_from_slice(&info.trailer());
        (info, out)
    }

    /// Signs `code` as firmware `version` for `board`.
    pub fn sign(code: &[u8], board: BoardId, version: Version, schema_hash: u64, key: &SigningKey) -> Image {
        let (info, signed) = Image::signed_bytes(code, board, version, schema_hash);
        let signature = key.sign(&digest(&signed)).to_bytes();
        Image { info, signed, signature }
    }

    /// Whether `key` signed it.
    pub fn verify(&self, key: &VerifyingKey) -> bool {
        key.verify(&digest(&self.signed), &ed25519_dalek::Signature::from_bytes(&self.signature)).is_ok()
    }

    /// The file's bytes.
    pub fn to_file(&self) -> Vec<u8> {
        let mut out = self.signed.clone();
        out.extend_from_slice(&self.signature);
        out
    }

    /// Reads an image file; what is wrong with it, in words.
    pub fn from_file(bytes: &[u8]) -> Result<Image, String> {
        let n = bytes.len();
        if n < 2 * TRAILER_LEN || !n.is_multiple_of(TRAILER_LEN) {
            return Err(format!(
                "{n} bytes: an image is a multiple of 64 bytes ending in a trailer and a signature \
                 (make one with `lightrig flash sign`)"
            ));
        }
        let (signed, sig) = bytes.split_at(n - 64);
        let at = signed.len() - TRAILER_LEN;
        let info = ImageInfo::from_trailer(&signed[at..])
            .ok_or("no image trailer before the signature (make the image with `lightrig flash sign`)")?;
        if info.trailer_at() as usize != at {
            return Err(format!(
                "the trailer says {} bytes of code, the file holds {at}: the file was cut or padded",
                info.code_len
            ));
        }
        let mut signature = [0; 64];
        signature.copy_from_slice(sig);
        Ok(Image { info, signed: signed.to_vec(), signature })
    }
}

/// A new signing key from the operating system's random source.
pub fn keygen() -> Result<SigningKey, String> {
    let mut secret = [0u8; 32];
    getrandom::getrandom(&mut secret).map_err(|e| format!("no random source to make a key from: {e}"))?;
    Ok(SigningKey::from_bytes(&secret))
}

/// A key file: 64 hex digits (whitespace around them ignored).
pub fn read_key(path: &Path) -> Result<[u8; 32], String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    parse_key(text.trim()).ok_or_else(|| {
        format!("{}: not a key (64 hex digits, as `lightrig flash keygen` writes)", path.display())
    })
}

/// 64 hex digits as 32 bytes.
pub fn parse_key(hex: &str) -> Option<[u8; 32]> {
    if hex.len() != 64 || !hex.is_ascii() {
        return None;
    }
    let mut out = [0; 32];
    for (k, b) in out.iter_mut().enumerate() {
        *b = u8::from_str_radix(&hex[2 * k..2 * k + 2], 16).ok()?;
    }
    Some(out)
}

/// 32 bytes as 64 hex digits.
pub fn key_hex(key: &[u8; 32]) -> String {
    key.iter().map(|b| format!("{b:02x}")).collect()
}

/// What went wrong sending an image.
#[derive(Debug)]
pub enum FlashError {
    /// The device or the link.
    Client(ClientError),
    /// The device answered something else than where the update stands.
    Unexpected(String),
}

impl std::fmt::Display for FlashError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FlashError::Client(e) => write!(f, "{e}"),
            FlashError::Unexpected(s) => f.write_str(s),
        }
    }
}

impl std::error::Error for FlashError {}

impl From<ClientError> for FlashError {
    fn from(e: ClientError) -> Self {
        FlashError::Client(e)
    }
}

/// How long a device may take to answer `cmd`: `Begin` erases the whole update slot (a
/// NUCLEO-G474RE's 118 pages take 2.6-4.7 s), `Finish` hashes the image and writes the marks,
/// `Cancel` and `Confirm` write marks; the rest answer at once.
pub fn answer_within_us(cmd: &UpdateCommand) -> u64 {
    match cmd {
        UpdateCommand::Begin(_) => 30_000_000,
        UpdateCommand::Finish(_) | UpdateCommand::Cancel | UpdateCommand::Confirm => 10_000_000,
        UpdateCommand::Status | UpdateCommand::Write { .. } => 2_000_000,
    }
}

/// One update command, answered with where the update stands.
pub fn update<T: Transport>(client: &mut Client<T>, cmd: UpdateCommand) -> Result<UpdateStatus, FlashError> {
    let within = answer_within_us(&cmd);
    match client.request_within(Command::Update(cmd), within)? {
        Reply::Update(s) => Ok(s),
        other => Err(FlashError::Unexpected(format!("an update command answered with {other:?}"))),
    }
}

/// Sends `image` (from where the device stands, if it was receiving this image already) and
/// finishes it: the device verifies it and marks it for the bootloader. `progress(sent,
/// total)` hears every chunk. Returns the device's status (`Ready`); the device resets into
/// the new image once it has sent that answer.
pub fn send<T: Transport>(
    client: &mut Client<T>,
    image: &Image,
    mut progress: impl FnMut(u32, u32),
) -> Result<UpdateStatus, FlashError> {
    let total = image.signed.len() as u32;
    let st = update(client, UpdateCommand::Begin(image.info))?;
    let mut at = match st.phase {
        UpdatePhase::Receiving { image: i, received } if i == image.info => received,
        other => return Err(FlashError::Unexpected(format!("Begin answered with phase {other:?}"))),
    };
    progress(at, total);
    while at < total {
        let end = (at as usize + UPDATE_CHUNK).min(image.signed.len());
        let data = HVec::from_slice(&image.signed[at as usize..end]).expect("a chunk fits");
        update(client, UpdateCommand::Write { offset: at, data })?;
        at = end as u32;
        progress(at, total);
    }
    update(client, UpdateCommand::Finish(Signature::from_bytes(&image.signature)))
}

/// After [`send`]: waits until the device has reset into its bootloader (its answers stop, or
/// come from a firmware that no longer knows this host), up to `timeout_us`; returns the
/// transport to connect again with.
pub fn await_reset<T: Transport>(mut client: Client<T>, timeout_us: u64) -> Result<T, FlashError> {
    let deadline = client.transport().now_us().saturating_add(timeout_us);
    while client.transport().now_us() < deadline {
        match client.request(Command::Update(UpdateCommand::Status)) {
            Ok(Reply::Update(UpdateStatus { phase: UpdatePhase::Ready { .. }, .. })) => {
                client.idle(50_000)?
            }
            Ok(other) => {
                return Err(FlashError::Unexpected(format!("before its reset the device answered {other:?}")))
            }
            // Gone or forgotten us: it reset.
            Err(_) => return Ok(client.into_transport()),
        }
    }
    Err(FlashError::Unexpected(format!(
        "the device did not reset within {} s of accepting the image; reset it by hand (the \
         bootloader swaps the image in then)",
        timeout_us / 1_000_000
    )))
}

/// Keeps the firmware the device runs (after an update's swap), else the bootloader swaps the
/// old one back at the next reset.
pub fn confirm<T: Transport>(client: &mut Client<T>) -> Result<UpdateStatus, FlashError> {
    update(client, UpdateCommand::Confirm)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v(major: u16) -> Version {
        Version { major, minor: 0, patch: 0 }
    }

    #[test]
    fn an_image_file_reads_back_and_verifies_with_its_key_only() {
        let key = SigningKey::from_bytes(&[3; 32]);
        let img = Image::sign(&[1, 2, 3, 4, 5], BoardId::Virtual, v(2), 77, &key);
        assert_eq!(img.signed.len(), 128);
        assert_eq!(img.info.code_len, 5);
        let back = Image::from_file(&img.to_file()).unwrap();
        assert_eq!(back, img);
        assert!(back.verify(&key.verifying_key()));
        assert!(!back.verify(&SigningKey::from_bytes(&[4; 32]).verifying_key()));
        let mut bent = img.clone();
        bent.signed[2] ^= 1;
        assert!(!bent.verify(&key.verifying_key()));
        // Cut, or not an image at all: said so.
        let file = img.to_file();
        assert!(Image::from_file(&file[..file.len() - 1]).unwrap_err().contains("multiple of 64"));
        assert!(Image::from_file(&[0; 192]).unwrap_err().contains("no image trailer"));
    }

    #[test]
    fn keys_are_64_hex_digits() {
        let k = [0xab; 32];
        assert_eq!(parse_key(&key_hex(&k)), Some(k));
        assert_eq!(parse_key("ab"), None);
        assert_eq!(parse_key(&"zz".repeat(32)), None);
    }
}
