//! The session format version `docs/session-format.md` gives against the one this host writes
//! (`FORMAT_VERSION`): the figure at the top, the manifest's `format` field and example, and
//! every "(format N)" that says when something was added. A reader written from the doc must
//! know the format the host writes. (The schema hash and protocol version in the same doc are
//! checked by `protocol/tests/docs_figures.rs`.)

use lightrig_host::session::FORMAT_VERSION;

const DOC: &str = "docs/session-format.md";

fn doc() -> String {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(DOC);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The decimal number at the start of `s`, and its length.
fn leading_number(s: &str) -> Option<(u32, usize)> {
    let n = s.bytes().take_while(u8::is_ascii_digit).count();
    s[..n].parse().ok().map(|v| (v, n))
}

/// Every `{before}N` in the doc: (line, what it says, N).
fn figures(text: &str, before: &str) -> Vec<(usize, String, u32)> {
    text.match_indices(before)
        .filter_map(|(at, _)| {
            let (n, len) = leading_number(&text[at + before.len()..])?;
            let line = text[..at].matches('\n').count() + 1;
            Some((line, text[at..at + before.len() + len].to_string(), n))
        })
        .collect()
}

#[test]
fn the_session_format_version_in_the_doc_is_the_one_the_host_writes() {
    let text = doc();
    let mut problems = Vec::new();
    // The figures that name the current format: each must be found, and say FORMAT_VERSION.
    for (before, what) in [
        ("Format version: **", "the format version at the top"),
        ("format version of the newest writer (", "the manifest's `format` field"),
        ("\"format\": ", "the manifest example"),
    ] {
        let found = figures(&text, before);
        if found.is_empty() {
            problems.push(format!(
                "{DOC}: {what} (`{before}N`) is not there any more: was the doc reworded? then teach this \
                 test the new wording"
            ));
        }
        for (line, says, n) in found {
            if n != FORMAT_VERSION {
                problems.push(format!(
                    "{DOC}:{line}: {what} says `{says}`; the host writes format {FORMAT_VERSION} (FORMAT_VERSION)"
                ));
            }
        }
    }
    // "(format N)": when a record or field was added. None can be newer than what the host
    // writes, and the newest must be it (else the doc misses what the last bump added).
    let added = figures(&text, "(format ");
    for (line, says, n) in &added {
        if *n > FORMAT_VERSION {
            problems.push(format!(
                "{DOC}:{line}: says `{says})`, a format newer than the host's {FORMAT_VERSION} (FORMAT_VERSION)"
            ));
        }
    }
    match added.iter().map(|(_, _, n)| *n).max() {
        Some(newest) if newest == FORMAT_VERSION => {}
        newest => problems.push(format!(
            "{DOC}: the newest \"(format N)\" is {newest:?}; nothing is marked as added in format \
             {FORMAT_VERSION}, the one the host writes (FORMAT_VERSION)"
        )),
    }
    assert!(problems.is_empty(), "session format figures:\n{}", problems.join("\n"));
}
