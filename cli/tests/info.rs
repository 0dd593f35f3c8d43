//! `lightrig info`: what a device says about itself, its link counters among it.

use std::process::Command;

#[test]
fn info_shows_the_devices_link_counters_datagrams_dropped_among_them() {
    let o = Command::new(env!("CARGO_BIN_EXE_lightrig")).args(["info", "--json"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let link = &v["link"];
    // The device's counters (GetStatus), every field of LinkStats.
    assert_eq!(link["datagrams_dropped"], 0, "{link}");
    assert!(link["frames_received"].as_u64().is_some_and(|n| n > 0), "{link}");
    assert_eq!(link["syncs"], 1, "{link}");
    let o = Command::new(env!("CARGO_BIN_EXE_lightrig")).args(["info"]).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    let line = text.lines().find(|l| l.starts_with("link ")).unwrap_or_else(|| panic!("{text}"));
    assert!(line.starts_with("link             since the device started: "), "{line}");
    assert!(line.ends_with("; epochs started 1; datagrams dropped 0"), "{line}");
}
