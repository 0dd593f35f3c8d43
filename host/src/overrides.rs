//! `--set KEY=VALUE`: a rig file's values changed for one run without editing the file.
//!
//! A lab runs its rig file as it is, but a first check (fewer views, a coarser gantry step, a
//! shorter sweep) or a scripted test wants a few values changed. An override names a key by
//! its path in the file (`plan.step_mm`, `plan.fit.board.cols`, `camera[0].pulse_us`: tables
//! by name, arrays of tables by position) and gives a TOML value (`4`, `[-4, 4]`,
//! `"cam0.json"`; a value that is not TOML is taken as a string). The file's text is edited
//! in place (comments and every other line kept, so errors still point at the file's own
//! lines), and a comment recording the overrides is appended: a session's manifest holds the
//! text that ran.

use std::fmt;
use std::str::FromStr;

use toml_edit::{DocumentMut, Item, Table, Value};

/// One `KEY=VALUE`.
#[derive(Debug, Clone, PartialEq)]
pub struct Override {
    /// The key's path, `plan.step_mm` or `camera[0].pulse_us`.
    pub key: String,
    /// The value as given.
    pub value: String,
}

impl FromStr for Override {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (key, value) = s.split_once('=').ok_or_else(|| {
            format!("`{s}`: expected KEY=VALUE, e.g. plan.step_mm=4 or camera[0].pulse_us=500")
        })?;
        let key = key.trim();
        if key.is_empty() || segments(key).is_err() {
            return Err(format!(
                "`{s}`: `{key}` is not a key path; give tables by name and arrays of tables by position, \
                 e.g. plan.fit.board.cols or camera[0].pulse_us"
            ));
        }
        Ok(Override { key: key.to_string(), value: value.trim().to_string() })
    }
}

impl fmt::Display for Override {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}={}", self.key, self.value)
    }
}

/// One step of a key path.
#[derive(Debug, Clone, PartialEq)]
enum Segment<'a> {
    Key(&'a str),
    Index(&'a str, usize),
}

fn segments(key: &str) -> Result<Vec<Segment<'_>>, ()> {
    key.split('.')
        .map(|part| {
            let ok = |n: &str| {
                !n.is_empty() && n.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            };
            match part.split_once('[') {
                None if ok(part) => Ok(Segment::Key(part)),
                Some((name, rest)) if ok(name) => {
                    let i = rest.strip_suffix(']').and_then(|i| i.parse().ok()).ok_or(())?;
                    Ok(Segment::Index(name, i))
                }
                _ => Err(()),
            }
        })
        .collect()
}

/// The rig file's `text` with `overrides` applied (in order), or what is wrong with one.
pub fn apply(text: &str, overrides: &[Override]) -> Result<String, String> {
    if overrides.is_empty() {
        return Ok(text.to_string());
    }
    let mut doc: DocumentMut =
        text.parse().map_err(|e: toml_edit::TomlError| format!("invalid TOML: {}", e.message()))?;
    for o in overrides {
        let value = if o.value.is_empty() {
            None
        } else {
            Some(o.value.parse().unwrap_or_else(|_| Value::from(o.value.as_str())))
        };
        set(doc.as_table_mut(), o, value)?;
    }
    let mut out = doc.to_string();
    if !out.ends_with('\n') {
        out.push('\n');
    }
    out += "\n# Overridden for this run (lightrig --set):\n";
    for o in overrides {
        out += &format!("#   {o}\n");
    }
    Ok(out)
}

/// Sets the key to `value`, or removes it (`None`).
fn set(root: &mut Table, o: &Override, value: Option<Value>) -> Result<(), String> {
    let path = segments(&o.key).map_err(|_| format!("--set {o}: `{}` is not a key path", o.key))?;
    let (last, tables) = path.split_last().ok_or_else(|| format!("--set {o}: no key"))?;
    let mut at: &mut Table = root;
    let mut walked = String::new();
    for seg in tables {
        let (name, index) = match *seg {
            Segment::Key(n) => (n, None),
            Segment::Index(n, i) => (n, Some(i)),
        };
        walked += &if walked.is_empty() { name.to_string() } else { format!(".{name}") };
        if !at.contains_key(name) {
            let mut t = Table::new();
            t.set_implicit(true);
            at.insert(name, Item::Table(t));
        }
        // An inline table (`board = { cols = 7, … }`) is edited as a table of its own.
        if let (Some(Item::Value(Value::InlineTable(_))), None) = (at.get(name), index) {
            if let Some(Item::Value(Value::InlineTable(inline))) = at.remove(name) {
                at.insert(name, Item::Table(inline.into_table()));
            }
        }
        at = match (at.get_mut(name), index) {
            (Some(Item::Table(t)), None) => t,
            (Some(Item::ArrayOfTables(a)), Some(i)) => {
                let n = a.len();
                a.get_mut(i).ok_or_else(|| {
                    format!(
                        "--set {o}: the file has {n} [[{name}]] table(s) ({name}[0]..{name}[{}])",
                        n.saturating_sub(1)
                    )
                })?
            }
            (_, Some(_)) => {
                return Err(format!("--set {o}: `{walked}` is not an array of tables ([[{name}]])"))
            }
            (_, None) => return Err(format!("--set {o}: `{walked}` is a value, not a table")),
        };
        if let Some(i) = index {
            walked += &format!("[{i}]");
        }
    }
    match *last {
        Segment::Key(k) => match value {
            None => match at.remove(k) {
                Some(_) => Ok(()),
                None => Err(format!("--set {o}: the file has no `{}` to remove", o.key)),
            },
            Some(value) => {
                if matches!(at.get(k), Some(Item::Table(_) | Item::ArrayOfTables(_))) {
                    return Err(format!("--set {o}: `{}` is a table; set one of its keys", o.key));
                }
                at.insert(k, Item::Value(value));
                Ok(())
            }
        },
        Segment::Index(..) => Err(format!("--set {o}: the last part of the key must be a name")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const RIG: &str = "# a rig\n[rig]\nname = \"x\" # kept\n\n[[camera]]\ncamera = 0\npulse_us = 100\n\n\
                       [[camera]]\ncamera = 1\npulse_us = 100\n\n[plan]\nstep_mm = 0.5\n\
                       fit = { board = { cols = 7 } }\n";

    fn o(s: &str) -> Override {
        s.parse().unwrap()
    }

    #[test]
    fn values_are_replaced_in_place_and_recorded() {
        let out = apply(RIG, &[o("plan.step_mm=4"), o("camera[1].pulse_us = 500"), o("plan.views=[1, 2]")])
            .unwrap();
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(lines[2], "name = \"x\" # kept");
        assert_eq!(lines[10], "pulse_us = 500", "{out}");
        assert_eq!(lines[6], "pulse_us = 100");
        assert_eq!(lines[13], "step_mm = 4");
        assert!(out.contains("views = [1, 2]"), "{out}");
        assert!(
            out.ends_with("#   plan.step_mm=4\n#   camera[1].pulse_us=500\n#   plan.views=[1, 2]\n"),
            "{out}"
        );
        let t: toml::Table = toml::from_str(&out).unwrap();
        assert_eq!(t["plan"]["step_mm"].as_integer(), Some(4));
    }

    #[test]
    fn inline_tables_new_tables_and_strings() {
        let out = apply(
            RIG,
            &[o("plan.fit.board.cols=9"), o("plan.calibrate.drive=0.1"), o("camera[0].response=cam0.json")],
        )
        .unwrap();
        let t: toml::Table = toml::from_str(&out).unwrap();
        assert_eq!(t["plan"]["fit"]["board"]["cols"].as_integer(), Some(9));
        assert_eq!(t["plan"]["calibrate"]["drive"].as_float(), Some(0.1));
        assert_eq!(t["camera"][0]["response"].as_str(), Some("cam0.json"));
        assert_eq!(apply(RIG, &[]).unwrap(), RIG, "no overrides, the text itself");
        // `KEY=` removes a key or a whole table.
        let out = apply(RIG, &[o("plan.step_mm="), o("camera[0].pulse_us=")]).unwrap();
        let t: toml::Table = toml::from_str(&out).unwrap();
        assert!(!t["plan"].as_table().unwrap().contains_key("step_mm"));
        assert!(!t["camera"][0].as_table().unwrap().contains_key("pulse_us"));
        let t: toml::Table = toml::from_str(&apply(RIG, &[o("plan=")]).unwrap()).unwrap();
        assert!(!t.contains_key("plan"));
        assert_eq!(
            apply(RIG, &[o("plan.nope=")]).unwrap_err(),
            "--set plan.nope=: the file has no `plan.nope` to remove"
        );
    }

    #[test]
    fn bad_overrides_say_what_is_wrong() {
        assert!("plan.step_mm".parse::<Override>().unwrap_err().contains("expected KEY=VALUE"));
        assert!("plan..x=1".parse::<Override>().unwrap_err().contains("not a key path"));
        assert_eq!(
            apply(RIG, &[o("camera[2].pulse_us=1")]).unwrap_err(),
            "--set camera[2].pulse_us=1: the file has 2 [[camera]] table(s) (camera[0]..camera[1])"
        );
        assert_eq!(
            apply(RIG, &[o("plan.step_mm.x=1")]).unwrap_err(),
            "--set plan.step_mm.x=1: `plan.step_mm` is a value, not a table"
        );
        assert_eq!(
            apply(RIG, &[o("plan[0].x=1")]).unwrap_err(),
            "--set plan[0].x=1: `plan` is not an array of tables ([[plan]])"
        );
        assert_eq!(
            apply(RIG, &[o("plan=1")]).unwrap_err(),
            "--set plan=1: `plan` is a table; set one of its keys"
        );
    }
}
