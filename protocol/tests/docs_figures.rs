//! The figures the docs give against this build: the schema hash, the protocol version, the
//! variant numbers of every enum `docs/protocol.md` lists (tables and inline lists), and the
//! unknown-tag bounds of §4.8.
//!
//! A client is written from the docs: a stale hash there is a client refused with
//! `SchemaMismatch`, a stale variant number one that sends or decodes the wrong message. The
//! variant numbers are taken from the wire: values of each enum are generated (`arbitrary`),
//! encoded with postcard, and the variant index read back from the first varint, until every
//! variant of the enum's schema has been seen. Every failure names the doc, the line, what it
//! says and what the build has. (The session format version is checked in
//! `host/tests/docs_figures.rs`, next to its constant.)

use std::collections::BTreeMap;
use std::fmt::Debug;
use std::path::{Path, PathBuf};

use arbitrary::{Arbitrary, Unstructured};
use lightrig_protocol::message::Message;
use lightrig_protocol::{DeviceMsg, HostMsg, PROTOCOL_VERSION, SCHEMA_HASH};
use postcard_schema::schema::DataModelType;
use postcard_schema::Schema;
use serde::Serialize;

// ------------------------------------------------------------------------------ the docs

/// The workspace root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

struct Doc {
    /// Path from the workspace root, for messages.
    name: String,
    text: String,
}

impl Doc {
    fn load(rel: &str) -> Doc {
        let path = root().join(rel);
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        Doc { name: rel.to_string(), text }
    }

    /// 1-based line of byte `offset`.
    fn line(&self, offset: usize) -> usize {
        self.text[..offset].matches('\n').count() + 1
    }

    /// `doc:line`.
    fn at(&self, offset: usize) -> String {
        format!("{}:{}", self.name, self.line(offset))
    }
}

/// Every Markdown file under `docs/`, and the README.
fn all_docs() -> Vec<Doc> {
    fn walk(dir: &Path, rel: &str, out: &mut Vec<String>) {
        let mut entries: Vec<_> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap()).collect();
        entries.sort_by_key(|e| e.file_name());
        for e in entries {
            let name = e.file_name().to_string_lossy().into_owned();
            let rel = format!("{rel}/{name}");
            if e.file_type().unwrap().is_dir() {
                walk(&e.path(), &rel, out);
            } else if name.ends_with(".md") {
                out.push(rel);
            }
        }
    }
    let mut names = vec!["README.md".to_string()];
    walk(&root().join("docs"), "docs", &mut names);
    names.iter().map(|n| Doc::load(n)).collect()
}

/// Fails with every problem found, one per line.
fn report(what: &str, problems: Vec<String>) {
    assert!(problems.is_empty(), "{what}: {} problem(s):\n{}", problems.len(), problems.join("\n"));
}

/// The largest char boundary of `text` at or below `i`.
fn floor_boundary(text: &str, mut i: usize) -> usize {
    while !text.is_char_boundary(i) {
        i -= 1;
    }
    i
}

/// The decimal number at the start of `s`, and its length in bytes.
fn leading_number(s: &str) -> Option<(u64, usize)> {
    let n = s.bytes().take_while(u8::is_ascii_digit).count();
    if n == 0 || s[n..].starts_with(|c: char| c.is_ascii_alphanumeric() || c == '_') {
        return None;
    }
    s[..n].parse().ok().map(|v| (v, n))
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// The identifier at the start of `s`.
fn leading_ident(s: &str) -> &str {
    let n = s.find(|c: char| !is_ident(c)).unwrap_or(s.len());
    &s[..n]
}

// ------------------------------------------------------------------------- schema hash

/// 64-bit figures in the docs that are not schema hashes, and what they are.
const OTHER_64BIT_FIGURES: &[(u64, &str)] =
    &[(0xcbf2_9ce4_8422_2325, "the FNV-1a offset basis (§6.2)"), (0, "an example board serial")];

/// Words that present the figure after them as the schema hash.
fn names_the_schema_hash(context: &str) -> bool {
    let c = context.to_ascii_lowercase();
    c.contains("schema hash") || c.contains("schema_hash")
}

/// The schema hash figures of `doc` that differ from the build's, into `problems`; returns how
/// many figures `doc` presents as the schema hash.
fn schema_hash_problems(doc: &Doc, problems: &mut Vec<String>) -> usize {
    let mut presented = 0;
    let t = &doc.text;
    // `0x` and exactly 16 hex digits: every 64-bit hex figure.
    for (at, _) in t.match_indices("0x") {
        if at > 0 && t[..at].ends_with(is_ident) {
            continue;
        }
        let digits = t[at + 2..].bytes().take_while(u8::is_ascii_hexdigit).count();
        if digits != 16 || t[at + 2 + digits..].starts_with(is_ident) {
            continue;
        }
        let figure = &t[at..at + 18];
        let value = u64::from_str_radix(&figure[2..], 16).unwrap();
        // The words just before it, since the last figure or sentence.
        let from = floor_boundary(t, at.saturating_sub(120));
        let mut context = &t[from..at];
        for stop in ["0x", ". ", ".\n", "\n\n", "|"] {
            if let Some(i) = context.rfind(stop) {
                context = &context[i + stop.len()..];
            }
        }
        if names_the_schema_hash(context) {
            presented += 1;
            if value != SCHEMA_HASH {
                problems.push(format!(
                    "{}: gives the schema hash as `{figure}`; this build's SCHEMA_HASH is 0x{SCHEMA_HASH:016x}",
                    doc.at(at)
                ));
            }
        } else if value != SCHEMA_HASH && !OTHER_64BIT_FIGURES.iter().any(|(v, _)| *v == value) {
            problems.push(format!(
                "{}: `{figure}` is neither this build's SCHEMA_HASH (0x{SCHEMA_HASH:016x}) nor a known \
                 other 64-bit figure: a stale schema hash? (if it is something else, add it to \
                 OTHER_64BIT_FIGURES with what it is)",
                doc.at(at)
            ));
        }
    }
    // The decimal form (`Debug` of a message, a JSON number): `schema_hash: 123…`.
    for (at, _) in t.match_indices("schema_hash") {
        let rest = &t[at + "schema_hash".len()..];
        let skip = rest.len() - rest.trim_start_matches(['"', '`', ':', ' ']).len();
        if !rest[..skip].contains(':') {
            continue;
        }
        if let Some((value, n)) = leading_number(&rest[skip..]) {
            presented += 1;
            if value != SCHEMA_HASH {
                problems.push(format!(
                    "{}: gives the schema hash as `{}`; this build's SCHEMA_HASH is {SCHEMA_HASH} \
                     (0x{SCHEMA_HASH:016x})",
                    doc.at(at),
                    &rest[skip..skip + n]
                ));
            }
        }
    }
    presented
}

#[test]
fn every_schema_hash_in_the_docs_is_this_builds() {
    let mut problems = Vec::new();
    let mut presented = BTreeMap::<String, usize>::new();
    for doc in all_docs() {
        let n = schema_hash_problems(&doc, &mut problems);
        presented.insert(doc.name.clone(), n);
    }
    // The figures this test exists for were found at all (a reworded doc must not make it pass
    // by finding nothing).
    for (doc, at_least) in [("docs/protocol.md", 2), ("docs/session-format.md", 2)] {
        let found = presented.get(doc).copied().unwrap_or(0);
        if found < at_least {
            problems.push(format!(
                "{doc}: found {found} schema hash figure(s), expected at least {at_least}: was the doc \
                 reworded? then teach this test the new wording"
            ));
        }
    }
    report("schema hash figures", problems);
}

// -------------------------------------------------------------------- protocol version

#[test]
fn every_protocol_version_in_the_docs_is_this_builds() {
    let mut problems = Vec::new();
    let mut found = BTreeMap::<String, usize>::new();
    for doc in all_docs() {
        let lower = doc.text.to_ascii_lowercase();
        for key in ["protocol_version", "protocol version"] {
            for (at, _) in lower.match_indices(key) {
                // `Protocol version: **1**`, `` `PROTOCOL_VERSION` = **1** ``,
                // `"protocol_version": 1`, `protocol_version: 1`, `# protocol_version = 1`.
                let rest = &doc.text[at + key.len()..];
                let skip = rest.len() - rest.trim_start_matches(['"', '`', ':', '=', ' ', '*']).len();
                let sep = &rest[..skip];
                if !(sep.contains(':') || sep.contains('=')) {
                    continue;
                }
                let Some((value, n)) = leading_number(&rest[skip..]) else { continue };
                *found.entry(doc.name.clone()).or_default() += 1;
                if value != u64::from(PROTOCOL_VERSION) {
                    problems.push(format!(
                        "{}: says `{}{}`; this build's PROTOCOL_VERSION is {PROTOCOL_VERSION}",
                        doc.at(at),
                        &doc.text[at..at + key.len()],
                        &rest[..skip + n]
                    ));
                }
            }
        }
    }
    for (doc, at_least) in [("docs/protocol.md", 2), ("docs/session-format.md", 2)] {
        let n = found.get(doc).copied().unwrap_or(0);
        if n < at_least {
            problems.push(format!(
                "{doc}: found {n} protocol version figure(s), expected at least {at_least}: was the doc \
                 reworded? then teach this test the new wording"
            ));
        }
    }
    report("protocol version figures", problems);
}

// ---------------------------------------------------------------- enum variant numbers

/// A small deterministic byte source for `arbitrary`.
struct XorShift(u64);

impl XorShift {
    fn fill(&mut self, bytes: &mut [u8]) {
        for b in bytes {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            *b = (self.0 >> 24) as u8;
        }
    }
}

/// The leading postcard varint of `bytes`.
fn varint(bytes: &[u8]) -> u32 {
    let mut v = 0u32;
    for (i, b) in bytes.iter().enumerate().take(5) {
        v |= u32::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            return v;
        }
    }
    panic!("no varint in {bytes:02x?}")
}

/// The variant names of enum `T` by wire index: values of `T` are generated and encoded with
/// postcard, and each one's variant index read from the first varint, until every variant the
/// schema names has been seen on the wire.
fn wire_variants<T>() -> Vec<String>
where
    T: for<'a> Arbitrary<'a> + Serialize + Schema + Debug,
{
    let DataModelType::Enum(schema) = T::SCHEMA.ty else { panic!("{} is not an enum", T::SCHEMA.name) };
    let mut seen: Vec<Option<String>> = vec![None; schema.len()];
    let mut rng = XorShift(0x2545_f491_4f6c_dd1d);
    let mut bytes = vec![0u8; 1024];
    for _ in 0..50_000 {
        if seen.iter().all(Option::is_some) {
            break;
        }
        rng.fill(&mut bytes);
        let Ok(value) = T::arbitrary(&mut Unstructured::new(&bytes)) else { continue };
        let encoded = postcard::to_allocvec(&value).expect("encodes");
        let index = varint(&encoded) as usize;
        let name = leading_ident(&format!("{value:?}")).to_string();
        assert!(
            index < seen.len(),
            "{}: {name} encodes as variant {index} of {}",
            T::SCHEMA.name,
            seen.len()
        );
        match &seen[index] {
            Some(other) => assert_eq!(*other, name, "{}: two variants encode as {index}", T::SCHEMA.name),
            None => seen[index] = Some(name),
        }
    }
    seen.into_iter()
        .enumerate()
        .map(|(i, name)| {
            let name = name.unwrap_or_else(|| panic!("{}: variant {i} never generated", T::SCHEMA.name));
            assert_eq!(
                name,
                schema[i].name,
                "{}: the wire and the schema disagree on variant {i}",
                T::SCHEMA.name
            );
            name
        })
        .collect()
}

/// Every enum the protocol doc lists, by the name the doc gives it: variant names by wire index.
fn wire_enums() -> BTreeMap<&'static str, Vec<String>> {
    use lightrig_protocol::{config, error, event, frame, link, message, sequence, session, update};
    let mut m = BTreeMap::new();
    macro_rules! enums {
        ($($name:literal => $t:ty),* $(,)?) => { $( m.insert($name, wire_variants::<$t>()); )* };
    }
    enums! {
        "Command" => message::Command,
        "DeviceMsg" => message::DeviceMsg,
        "Reply" => message::Reply,
        "Error" => error::Error,
        "Peripheral" => error::Peripheral,
        "FrameError" => frame::FrameError,
        "FrameKind" => link::FrameKind,
        "ConfigItem" => config::ConfigItem,
        "ConfigField" => config::ConfigField,
        "InvalidReason" => config::InvalidReason,
        "Polarity" => config::Polarity,
        "Input" => config::Input,
        "DacKind" => config::DacKind,
        "AxisKind" => config::AxisKind,
        "HomingMode" => config::HomingMode,
        "Action" => sequence::Action,
        "AxisRef" => sequence::AxisRef,
        "WaitFor" => sequence::WaitFor,
        "StartAt" => sequence::StartAt,
        "Event" => event::Event,
        "FaultCause" => event::FaultCause,
        "DeviceState" => event::DeviceState,
        "Switch" => event::Switch,
        "LogLevel" => event::LogLevel,
        "BoardId" => session::BoardId,
        "ResetCause" => session::ResetCause,
        "UpdateCommand" => update::UpdateCommand,
        "UpdatePhase" => update::UpdatePhase,
        "UpdateError" => update::UpdateError,
        "Result" => Result<u8, u8>,
    }
    m
}

/// One enum as a doc lists it: (index, variant name, byte offset of the entry).
struct Listing {
    ty: String,
    /// Offset of the table header or the list, for messages.
    at: usize,
    entries: Vec<(u32, String, usize)>,
}

/// The cells of a Markdown table row (pipes inside backticks are text).
fn cells(row: &str) -> Vec<(usize, &str)> {
    let mut out = Vec::new();
    let mut code = false;
    let mut start = None;
    for (i, c) in row.char_indices() {
        match c {
            '`' => code = !code,
            '|' if !code => {
                if let Some(s) = start {
                    out.push((s, &row[s..i]));
                }
                start = Some(i + 1);
            }
            _ => {}
        }
    }
    out
}

/// `N `Name`` pairs in `text` (a list such as "0 `Galvo`, 1 `Laser`"), with their offsets.
fn pairs(text: &str, base: usize) -> Vec<(u32, String, usize)> {
    let mut out = Vec::new();
    for (i, _) in text.match_indices(|c: char| c.is_ascii_digit()) {
        if i > 0 && text[..i].ends_with(|c: char| is_ident(c) || c == '.' || c == '-') {
            continue;
        }
        let Some((n, len)) = leading_number(&text[i..]) else { continue };
        let rest = &text[i + len..];
        if let Some(name) = rest.strip_prefix(" `") {
            let name = leading_ident(name);
            if !name.is_empty() {
                out.push((n as u32, name.to_string(), base + i));
            }
        }
    }
    out
}

/// The type a `| idx | name |` table at line `k` lists: the bold `**`X`**` or the `` `X`: ``
/// just above it, else the `(`X`)` of the section heading.
fn table_type(lines: &[(usize, &str)], k: usize) -> Option<String> {
    let mut first = true;
    for &(_, line) in lines[..k].iter().rev() {
        let l = line.trim();
        if l.is_empty() {
            continue;
        }
        if first {
            first = false;
            if let Some(r) = l.strip_prefix("**`") {
                return Some(leading_ident(r).to_string());
            }
            if l.starts_with('`') && l.ends_with("`:") {
                return Some(leading_ident(&l[1..]).to_string());
            }
        }
        if l.starts_with('#') {
            let open = l.rfind("(`")?;
            return Some(leading_ident(&l[open + 2..]).to_string());
        }
    }
    None
}

/// Every enum listing of the protocol doc: `| idx | name |` tables, `| type | encoding |` rows,
/// `**`X`**: 0 `A`, 1 `B` …` paragraphs and `` `field: X` (0 `A`, …) `` lists.
fn listings(doc: &Doc, known: &BTreeMap<&str, Vec<String>>, problems: &mut Vec<String>) -> Vec<Listing> {
    let t = &doc.text;
    let mut lines = Vec::new();
    let mut off = 0;
    for line in t.split('\n') {
        lines.push((off, line));
        off += line.len() + 1;
    }
    let mut out = Vec::new();
    let mut k = 0;
    while k < lines.len() {
        let (at, line) = lines[k];
        let header: Vec<String> = cells(line).iter().map(|(_, c)| c.trim().to_string()).collect();
        let is_idx = header.len() >= 2 && header[0] == "idx" && header[1] == "name";
        let is_encoding = header.len() == 2 && header[0] == "type" && header[1] == "encoding";
        if !(is_idx || is_encoding) {
            k += 1;
            continue;
        }
        let ty = if is_idx { table_type(&lines, k) } else { None };
        if is_idx && ty.is_none() {
            problems
                .push(format!("{}: cannot tell which enum this `| idx | name |` table lists", doc.at(at)));
        }
        let mut listing = ty.map(|ty| Listing { ty, at, entries: Vec::new() });
        k += 1;
        while k < lines.len() && lines[k].1.trim_start().starts_with('|') {
            let (row_at, row) = lines[k];
            k += 1;
            let c = cells(row);
            if c.len() < 2 || c[0].1.trim().starts_with("---") {
                continue;
            }
            if is_idx {
                let Some(listing) = listing.as_mut() else { continue };
                let (idx, name) = (c[0].1.trim(), c[1].1.trim());
                match (idx.parse::<u32>(), name.strip_prefix('`')) {
                    (Ok(i), Some(n)) => listing.entries.push((i, leading_ident(n).to_string(), row_at)),
                    _ => problems.push(format!(
                        "{}: cannot read the row `{}` as `| index | `Name` | …`",
                        doc.at(row_at),
                        row.trim()
                    )),
                }
            } else {
                // `| `X` | 0 `A` (…), 1 `B` |`; rows of structs say `struct …`.
                let ty = c[0].1.trim().trim_matches('`');
                let enc = c[1].1;
                if enc.trim_start().starts_with(|ch: char| ch.is_ascii_digit()) {
                    let entries = pairs(enc, row_at + c[1].0);
                    out.push(Listing { ty: ty.to_string(), at: row_at, entries });
                }
            }
        }
        out.extend(listing);
    }
    // `**`X`**: 0 `A`, …` / `**`X`** (enum): 0 `A`, …` paragraphs.
    for (p_at, para) in paragraphs(t) {
        let Some(r) = para.strip_prefix("**`") else { continue };
        let ty = leading_ident(r);
        let after = &r[ty.len()..];
        let Some(after) = after.strip_prefix("`**") else { continue };
        if !(after.starts_with(':') || after.starts_with(" (enum")) || !known.contains_key(ty) {
            continue;
        }
        let entries = pairs(after, p_at + (para.len() - after.len()));
        if !entries.is_empty() {
            out.push(Listing { ty: ty.to_string(), at: p_at, entries });
        }
    }
    // `` `field: X` (0 `A`, 1 `B`, …) `` inside a struct's description.
    for (at, _) in t.match_indices(": ") {
        let before = &t[..at];
        let Some(open) = before.rfind('`') else { continue };
        if !before[open + 1..].chars().all(is_ident) {
            continue;
        }
        let rest = &t[at + 2..];
        let ty = leading_ident(rest);
        let Some(list) = rest[ty.len()..].strip_prefix("` (0 `") else { continue };
        if !known.contains_key(ty) {
            continue;
        }
        let start = at + 2 + ty.len() + 3;
        let mut depth = 1;
        let end = list.char_indices().find_map(|(i, c)| {
            match c {
                '(' => depth += 1,
                ')' => depth -= 1,
                _ => {}
            }
            (depth == 0).then_some(i)
        });
        let body = &t[start..start + 3 + end.unwrap_or(list.len())];
        out.push(Listing { ty: ty.to_string(), at: start, entries: pairs(body, start) });
    }
    out
}

/// Paragraphs (runs of non-blank lines) with their offsets.
fn paragraphs(t: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut off = 0;
    let mut cur: Option<(usize, String)> = None;
    for line in t.split('\n') {
        if line.trim().is_empty() {
            out.extend(cur.take());
        } else {
            match &mut cur {
                Some((_, p)) => {
                    p.push('\n');
                    p.push_str(line);
                }
                None => cur = Some((off, line.to_string())),
            }
        }
        off += line.len() + 1;
    }
    out.extend(cur);
    out
}

/// Checks every variant number `doc` gives against the wire: its listings (tables and lists),
/// then the numbers in its text. Returns what it read, for the caller to check that it found
/// what it should: (listings, numbers in the text).
fn variant_problems(
    doc: &Doc,
    wire: &BTreeMap<&'static str, Vec<String>>,
    problems: &mut Vec<String>,
) -> (Vec<Listing>, usize) {
    let found = listings(doc, wire, problems);
    for l in &found {
        let Some(variants) = wire.get(l.ty.as_str()) else {
            problems.push(format!(
                "{}: lists the variants of `{}`, which this test does not know: add it to wire_enums()",
                doc.at(l.at),
                l.ty
            ));
            continue;
        };
        for (idx, name, at) in &l.entries {
            match variants.iter().position(|v| v == name) {
                Some(i) if i as u32 == *idx => {}
                Some(i) => problems.push(format!(
                    "{}: says `{}::{name}` is {idx}; on the wire it is {i}",
                    doc.at(*at),
                    l.ty
                )),
                None => problems.push(format!(
                    "{}: says {idx} is `{}::{name}`; the build's {} has no such variant ({idx} is `{}`)",
                    doc.at(*at),
                    l.ty,
                    l.ty,
                    variants.get(*idx as usize).map_or("none", String::as_str)
                )),
            }
        }
        // A list leaves none out: a client written from it must know every variant.
        for (i, v) in variants.iter().enumerate() {
            if !l.entries.iter().any(|(_, n, _)| n == v) {
                problems.push(format!(
                    "{}: the list of `{}` leaves out `{v}`, which the build has as {i}",
                    doc.at(l.at),
                    l.ty
                ));
            }
        }
    }
    // Variant numbers given in the text: `` `Command::Update` (index 14) ``, `` `Reply::Hello` =
    // index 0 ``, `` `Result::Ok` = 0 ``, and a bare `(5)` right after one of those in a list.
    let flat = doc.text.replace('\n', " ");
    let mut mentions = 0;
    let mut last_end = None;
    for (at, _) in flat.match_indices('`') {
        let r = &flat[at + 1..];
        let ty = leading_ident(r);
        let Some(r) = r[ty.len()..].strip_prefix("::") else { continue };
        let variant = leading_ident(r);
        let Some(after) = r[variant.len()..].strip_prefix('`') else { continue };
        let Some(variants) = wire.get(ty) else { continue };
        let end = at + 1 + ty.len() + 2 + variant.len() + 1;
        let mut number = None;
        for p in [" (index ", " = index ", " = "] {
            if let Some(r) = after.strip_prefix(p) {
                number = Some((p.len(), r));
                break;
            }
        }
        if number.is_none() && last_end.is_some_and(|e| flat[e..at].trim() == ",") {
            number = after.strip_prefix(" (").map(|r| (2, r));
        }
        let Some((prefix, r)) = number else { continue };
        let Some((idx, len)) = leading_number(r) else { continue };
        last_end = Some(end + prefix + len + usize::from(r[len..].starts_with(')')));
        mentions += 1;
        match variants.iter().position(|v| v == variant) {
            Some(i) if i as u64 == idx => {}
            Some(i) => problems
                .push(format!("{}: says `{ty}::{variant}` is {idx}; on the wire it is {i}", doc.at(at))),
            None => problems.push(format!("{}: the build's `{ty}` has no variant `{variant}`", doc.at(at))),
        }
    }
    (found, mentions)
}

#[test]
fn every_variant_number_the_protocol_doc_lists_is_the_wire_index() {
    let doc = Doc::load("docs/protocol.md");
    let wire = wire_enums();
    let mut problems = Vec::new();
    let (found, mentions) = variant_problems(&doc, &wire, &mut problems);
    // What was read (shown with `--nocapture`), to see at a glance that nothing was skipped.
    for l in &found {
        println!("{}: {} ({} entries)", doc.at(l.at), l.ty, l.entries.len());
    }
    // The tables this test exists for were found and read.
    for ty in ["Command", "Error", "DeviceMsg", "Reply"] {
        if !found.iter().any(|l| l.ty == ty && !l.entries.is_empty()) {
            problems.push(format!(
                "docs/protocol.md: no table of `{ty}` found: was the doc reworded? then teach this test the \
                 new layout"
            ));
        }
    }
    if mentions < 4 {
        problems.push(format!(
            "docs/protocol.md: found {mentions} variant numbers in the text (`Command::Update` (index …), …), \
             expected at least 4: was the doc reworded?"
        ));
    }
    report("variant numbers in docs/protocol.md", problems);
}

/// The checks above on a doc with known stale figures: each one is caught, at its line.
#[test]
fn the_checks_catch_stale_figures() {
    let text = "\
Schema hash of this revision: `0x7250784ad59713e5`.

**`Command`** (enum)

| idx | name | content |
|---|---|---|
| 0 | `Hello` | `{ protocol_version: u16, schema_hash: u64 }` |
| 1 | `GetClock` | — |
| 2 | `GetStatus` | — |
| 3 | `Heartbeat` | — |
| 4 | `Configure` | `(ConfigItem)` |
| 5 | `Arm` | `{ lasers: u8 }` |
| 6 | `Disarm` | — |
| 7 | `EmergencyStop` | — |
| 8 | `ClearFault` | — |
| 9 | `Home` | `(AxisRef)` |
| 10 | `Immediate` | `(Action)` |
| 11 | `SequenceLoad` | `(Chunk)` |
| 12 | `SequenceStart` | `{ sequence: u32, at: StartAt }` |
| 13 | `Update` | `(UpdateCommand)` |

**`Peripheral`**: 0 `Galvo`, 1 `Laser`, 2 `Stepper`, 3 `FilterWheel`, 4 `VoiceCoil`, 6 `Camera`.

Frozen: `Command::Update` (index 13), `Reply::Update` (5), `Error::Update` (16).
";
    let doc = Doc { name: "stale.md".into(), text: text.into() };
    let mut problems = Vec::new();
    assert_eq!(schema_hash_problems(&doc, &mut problems), 1);
    let wire = wire_enums();
    let (found, mentions) = variant_problems(&doc, &wire, &mut problems);
    assert_eq!((found.len(), mentions), (2, 3));
    let want = [
        "stale.md:1: gives the schema hash as `0x7250784ad59713e5`",
        "stale.md:20: says `Command::Update` is 13; on the wire it is 14",
        "stale.md:5: the list of `Command` leaves out `SequenceAbort`, which the build has as 13",
        "stale.md:22: says `Peripheral::Camera` is 6; on the wire it is 5",
        "stale.md:24: says `Command::Update` is 13; on the wire it is 14",
        "stale.md:24: says `Error::Update` is 16; on the wire it is 17",
    ];
    for w in want {
        assert!(
            problems.iter().any(|p| p.starts_with(w)),
            "not reported: {w}\ngot:\n{}",
            problems.join("\n")
        );
    }
    assert_eq!(problems.len(), want.len(), "{}", problems.join("\n"));
}

// ----------------------------------------------------------------- §4.8 tag bounds

/// The smallest tag `encode(tag)` makes an unknown message type, as the build classifies it.
fn first_unknown(unknown: impl Fn(u8) -> bool) -> u32 {
    (0..=127u8).find(|&k| unknown(k)).expect("some tag below 128 is unknown") as u32
}

#[test]
fn the_unknown_tag_bounds_in_the_protocol_doc_are_the_builds() {
    let doc = Doc::load("docs/protocol.md");
    let wire = wire_enums();
    // The build's bounds: what its decoder calls an unknown type, and the variant counts.
    let command = first_unknown(|k| <HostMsg as Message>::unknown_tag(&[0, k]));
    let device = first_unknown(|k| <DeviceMsg as Message>::unknown_tag(&[k]));
    assert_eq!(
        command as usize,
        wire["Command"].len(),
        "HostMsg: the first unknown tag is the variant count"
    );
    assert_eq!(
        device as usize,
        wire["DeviceMsg"].len(),
        "DeviceMsg: the first unknown tag is the variant count"
    );
    let kinds = wire["FrameKind"].len() as u64;
    assert_eq!(kinds, u64::from(lightrig_protocol::link::FRAME_KIND_COUNT));
    let mut problems = Vec::new();
    for (wording, build, what) in [
        ("the command index after the `id` varint is ≥ ", u64::from(command), "Command variants"),
        ("for `DeviceMsg`: the first varint is ≥ ", u64::from(device), "DeviceMsg variants"),
        ("the first byte (the `kind`) is ≥ ", kinds, "FrameKind variants"),
        ("first header byte ≥ ", kinds, "FrameKind variants"),
        ("`FRAME_KIND_COUNT` = ", kinds, "FrameKind variants"),
    ] {
        let flat = doc.text.replace('\n', " ");
        let hits: Vec<usize> = flat.match_indices(wording).map(|(i, _)| i).collect();
        if hits.is_empty() {
            problems.push(format!(
                "docs/protocol.md: the wording `{wording}N` is gone: was the doc reworded? then teach this test \
                 the new wording"
            ));
        }
        for at in hits {
            match leading_number(&flat[at + wording.len()..]) {
                Some((n, _)) if n == build => {}
                Some((n, _)) => problems.push(format!(
                    "{}: says `{wording}{n}`; the build has {build} {what}, so the first unknown index is {build}",
                    doc.at(at),
                )),
                None => problems.push(format!("{}: no number after `{wording}`", doc.at(at))),
            }
        }
    }
    report("unknown-tag bounds in docs/protocol.md", problems);
}
