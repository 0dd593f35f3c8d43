//! `lightrig flash` end to end on the virtual device: keys, a signed image, the update sent,
//! swapped in at the reset and confirmed; images signed with another key or built for
//! another board refused with what to do.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn lightrig(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lightrig")).current_dir(dir).args(args).output().unwrap()
}

fn scratch() -> PathBuf {
    let d = std::env::temp_dir().join(format!("lightrig-flash-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn said(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn a_signed_image_is_sent_swapped_in_and_confirmed_and_bad_ones_are_refused() {
    let dir = scratch();
    let code: Vec<u8> = (0..30_000u32).map(|k| (k * 7 % 251) as u8).collect();
    std::fs::write(dir.join("fw.bin"), &code).unwrap();
    let sign = |key: &[&str], board: &str, version: &str, out: &str| {
        let mut args = vec!["flash", "sign", "fw.bin", "--board", board, "--version", version, "-o", out];
        args.extend_from_slice(key);
        lightrig(&dir, &args)
    };
    let o = sign(&["--virtual-key"], "virtual", "0.4.2", "good.lrfw");
    assert!(o.status.success(), "{}", said(&o));
    assert!(said(&o).contains("0.4.2 for Virtual (30000 bytes of code, 30080 signed)"), "{}", said(&o));
    // 30000 bytes of code, 16 of padding (to a multiple of 64), 64 of trailer, 64 of signature.
    assert_eq!(std::fs::metadata(dir.join("good.lrfw")).unwrap().len(), 30_144);

    let o = lightrig(&dir, &["flash", "good.lrfw", "--connect", "virtual"]);
    let s = said(&o);
    assert!(o.status.success(), "{s}");
    assert!(s.contains("Virtual, firmware 0.1.0"), "{s}");
    assert!(s.contains("the device verified the signature and resets into it"), "{s}");
    assert!(s.contains("running 0.4.2 (confirmed); fallback 0.1.0 for Virtual"), "{s}");

    // Left unconfirmed, it says what happens next.
    let o = lightrig(&dir, &["flash", "good.lrfw", "--no-confirm"]);
    assert!(
        said(&o).contains("running 0.4.2 (unconfirmed: swapped back at the next reset, or in 60 s)"),
        "{}",
        said(&o)
    );

    // A lab's own key: the virtual board does not trust it.
    let o = lightrig(&dir, &["flash", "keygen", "lab"]);
    assert!(o.status.success(), "{}", said(&o));
    let public = std::fs::read_to_string(dir.join("lab.pub")).unwrap();
    assert_eq!(public.trim().len(), 64);
    let o = lightrig(&dir, &["flash", "keygen", "lab"]);
    assert_eq!(o.status.code(), Some(2), "a key is never overwritten: {}", said(&o));
    let o = sign(&["--key", "lab.key"], "virtual", "0.5.0", "lab.lrfw");
    assert!(o.status.success(), "{}", said(&o));
    let o = lightrig(&dir, &["flash", "lab.lrfw"]);
    assert_eq!(o.status.code(), Some(3), "{}", said(&o));
    assert!(
        said(&o).contains("refused the signature") && said(&o).contains("runs what it ran"),
        "{}",
        said(&o)
    );

    // Built for another board: refused before anything is sent.
    let o = sign(&["--key", "lab.key"], "nucleo-g474re", "0.5.0", "nucleo.lrfw");
    assert!(o.status.success());
    let o = lightrig(&dir, &["flash", "nucleo.lrfw"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(said(&o).contains("the image is for NucleoG474re, the device is a Virtual"), "{}", said(&o));

    // Not an image.
    let o = lightrig(&dir, &["flash", "fw.bin"]);
    assert_eq!(o.status.code(), Some(4));
    assert!(said(&o).contains("fw.bin: 30000 bytes: an image is a multiple of 64 bytes"), "{}", said(&o));

    // `lightrig info` shows the images the device holds.
    let o = Command::new(env!("CARGO_BIN_EXE_lightrig")).args(["info"]).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("update           running 0.1.0, fallback none, Idle, slot 65536 bytes"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}
