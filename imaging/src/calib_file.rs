//! The calibration file: a camera's intrinsics and distortion, the views they were fitted to, and
//! optionally the pose of a board on the rig's reference plane. Written by `lightrig calibrate`,
//! read by the pipelines. Format: TOML, `format = "lightrig-calibration"`, `version = 1`,
//! documented in `docs/calibration-format.md`.
//!
//! TOML rather than JSON: the rig files are TOML, so one parser and one error style (file, line,
//! field) serve both; comments let the file carry its units beside the numbers; and a person
//! reviewing a calibration reads and diffs it line by line.
//!
//! The writer is deterministic (no dates, fixed key order, floats in Rust's shortest round-trip
//! form), so a calibration re-run on the same images gives the same bytes, and every value read
//! back is the exact `f64` written. The reader refuses unknown keys (a misspelt key would
//! otherwise be silently ignored), non-finite numbers and impossible values, naming the file,
//! the line and the field.

use std::fmt;
use std::io::Write;
use std::path::{Path, PathBuf};

use toml::de::{DeArray, DeTable, DeValue};
use toml::Spanned;

use crate::calib::{Board, Intrinsics, Pose};

/// The `format` key's value.
pub const FORMAT: &str = "lightrig-calibration";
/// The format version this build writes and reads.
pub const VERSION: i64 = 1;

/// A calibration file's contents.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationFile {
    /// What wrote it, e.g. `lightrig 0.1.0` (provenance; no date, so outputs are reproducible).
    pub tool: String,
    /// Image size in pixels `(width, height)` the intrinsics belong to.
    pub image_size: (u32, u32),
    /// Pinhole intrinsics and OpenCV's 5-coefficient distortion (see [`crate::calib`]).
    pub intrinsics: Intrinsics,
    /// The calibration board.
    pub board: BoardSpec,
    /// Reprojection RMS over all corners of all views, pixels.
    pub rms: f64,
    /// The views the intrinsics were fitted to, in input order.
    pub views: Vec<View>,
    /// Images given for calibration in which no board was found (skipped on request).
    pub skipped: Vec<String>,
    /// The pose of a board lying on the rig's reference plane, if registered.
    pub reference: Option<Reference>,
}

/// A chessboard: inner corners and square size ([`Board::chessboard`]'s geometry).
#[derive(Debug, Clone, PartialEq)]
pub struct BoardSpec {
    /// Inner corners per row.
    pub cols: usize,
    /// Inner corners per column.
    pub rows: usize,
    /// Side of a square, in `unit`; poses' translations are in the same unit.
    pub square: f64,
    /// The length unit, e.g. `mm` (informational).
    pub unit: String,
}

impl BoardSpec {
    /// The board's corner positions.
    pub fn board(&self) -> Board {
        Board::chessboard(self.cols, self.rows, self.square)
    }
}

/// One calibration image: its file, its board → camera pose and its reprojection RMS.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    pub file: String,
    pub rms: f64,
    pub pose: Pose,
}

/// A board on the rig's reference plane (the linear light source registration): its file, its
/// geometry (it need not be the calibration board), its board → camera pose and RMS.
#[derive(Debug, Clone, PartialEq)]
pub struct Reference {
    pub file: String,
    pub board: BoardSpec,
    pub rms: f64,
    pub pose: Pose,
}

/// What was wrong, where: `path:line: field: message` (line and field when known).
#[derive(Debug, Clone, PartialEq)]
pub struct CalibFileError {
    pub path: PathBuf,
    /// 1-based line of the offending key or value (of the table header for a missing key).
    pub line: Option<usize>,
    /// Dotted key path, e.g. `intrinsics.fx` or `view[2].rvec`; empty for file-level errors.
    pub field: String,
    pub message: String,
}

impl fmt::Display for CalibFileError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.path.display())?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if !self.field.is_empty() {
            write!(f, ": {}", self.field)?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for CalibFileError {}

// ---------------------------------------------------------------------------------------------
// Writing.

/// The file's text. Fails (naming the field) on non-finite numbers or impossible values, which
/// the reader would refuse.
pub fn to_toml(c: &CalibrationFile) -> Result<String, (String, String)> {
    validate(c)?;
    let mut s = String::new();
    let k = &c.intrinsics;
    s += "# lightrig camera calibration; format: docs/calibration-format.md\n";
    s += &format!("format = {}\nversion = {VERSION}\ntool = {}\n", quote(FORMAT), quote(&c.tool));
    s += "\n[image]\n# pixels\n";
    s += &format!("width = {}\nheight = {}\n", c.image_size.0, c.image_size.1);
    s += "\n[intrinsics]\n# pixels; pixel centres at integer coordinates; no skew\n";
    s += &format!("fx = {:?}\nfy = {:?}\ncx = {:?}\ncy = {:?}\n", k.fx, k.fy, k.cx, k.cy);
    s += "\n[distortion]\n# OpenCV's model: radial k1 k2 k3, tangential p1 p2, on normalised coordinates\n";
    s += &format!("k1 = {:?}\nk2 = {:?}\np1 = {:?}\np2 = {:?}\nk3 = {:?}\n", k.k1, k.k2, k.p1, k.p2, k.k3);
    s += "\n[board]\n# inner corners; square side in `unit`, which poses' translations share\n";
    write_board(&mut s, &c.board);
    s += "\n[fit]\n# reprojection RMS over all corners of all views, pixels\n";
    s += &format!("rms = {:?}\n", c.rms);
    s += &format!("skipped = {}\n", string_array(&c.skipped));
    if !c.views.is_empty() {
        s += "\n# One [[view]] per image. Poses are board -> camera, Xc = R(rvec)·X + tvec:\n";
        s += "# rvec a Rodrigues vector (radians), tvec in board units.\n";
    }
    for (i, v) in c.views.iter().enumerate() {
        s += if i == 0 { "[[view]]\n" } else { "\n[[view]]\n" };
        s += &format!("file = {}\nrms = {:?}\n", quote(&v.file), v.rms);
        write_pose(&mut s, &v.pose);
    }
    if let Some(r) = &c.reference {
        s += "\n# A board on the rig's reference plane; pose as for the views.\n[reference]\n";
        s += &format!("file = {}\n", quote(&r.file));
        write_board(&mut s, &r.board);
        s += &format!("rms = {:?}\n", r.rms);
        write_pose(&mut s, &r.pose);
    }
    Ok(s)
}

/// Writes the file (through a temporary file renamed into place).
pub fn write(path: impl AsRef<Path>, c: &CalibrationFile) -> Result<(), CalibFileError> {
    let path = path.as_ref();
    let text = to_toml(c).map_err(|(field, message)| CalibFileError {
        path: path.into(),
        line: None,
        field,
        message: format!("{message}; not written"),
    })?;
    crate::io::write_atomically(path, |out| out.write_all(text.as_bytes()).map_err(|e| e.to_string()))
        .map_err(|e| CalibFileError {
            path: path.into(),
            line: None,
            field: String::new(),
            message: e.to_string(),
        })
}

fn write_board(s: &mut String, b: &BoardSpec) {
    *s += &format!(
        "cols = {}\nrows = {}\nsquare = {:?}\nunit = {}\n",
        b.cols,
        b.rows,
        b.square,
        quote(&b.unit)
    );
}

fn write_pose(s: &mut String, p: &Pose) {
    let v = |a: [f64; 3]| format!("[{:?}, {:?}, {:?}]", a[0], a[1], a[2]);
    *s += &format!("rvec = {}\ntvec = {}\n", v(p.rvec), v(p.tvec));
}

/// A TOML basic string.
fn quote(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 2);
    out.push('"');
    for ch in text.chars() {
        match ch {
            '"' => out += "\\\"",
            '\\' => out += "\\\\",
            '\n' => out += "\\n",
            '\t' => out += "\\t",
            '\r' => out += "\\r",
            c if (c as u32) < 0x20 || c as u32 == 0x7f => out += &format!("\\u{:04X}", c as u32),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

fn string_array(items: &[String]) -> String {
    let inner: Vec<String> = items.iter().map(|i| quote(i)).collect();
    format!("[{}]", inner.join(", "))
}

/// The checks the reader applies to values, as `(field, message)`.
fn validate(c: &CalibrationFile) -> Result<(), (String, String)> {
    let err = |f: &str, m: &str| Err((f.to_string(), m.to_string()));
    if c.image_size.0 == 0 || c.image_size.1 == 0 {
        return err("image", "width and height must be positive");
    }
    let k = &c.intrinsics;
    for (name, v) in [("fx", k.fx), ("fy", k.fy)] {
        if !(v.is_finite() && v > 0.0) {
            return err(&format!("intrinsics.{name}"), &format!("{v} is not a positive focal length"));
        }
    }
    for (name, v) in [("intrinsics.cx", k.cx), ("intrinsics.cy", k.cy), ("fit.rms", c.rms)] {
        if !v.is_finite() {
            return err(name, &format!("{v} is not finite"));
        }
    }
    for (name, v) in [("k1", k.k1), ("k2", k.k2), ("p1", k.p1), ("p2", k.p2), ("k3", k.k3)] {
        if !v.is_finite() {
            return err(&format!("distortion.{name}"), &format!("{v} is not finite"));
        }
    }
    check_board(&c.board, "board")?;
    for (i, v) in c.views.iter().enumerate() {
        check_pose(&v.pose, v.rms, &format!("view[{i}]"))?;
    }
    if let Some(r) = &c.reference {
        check_board(&r.board, "reference")?;
        check_pose(&r.pose, r.rms, "reference")?;
    }
    Ok(())
}

fn check_board(b: &BoardSpec, at: &str) -> Result<(), (String, String)> {
    if b.cols < 2 || b.rows < 2 {
        return Err((
            format!("{at}.cols"),
            format!("a {}×{} board: need at least 2×2 inner corners", b.cols, b.rows),
        ));
    }
    if !(b.square.is_finite() && b.square > 0.0) {
        return Err((format!("{at}.square"), format!("{} is not a positive square size", b.square)));
    }
    Ok(())
}

fn check_pose(p: &Pose, rms: f64, at: &str) -> Result<(), (String, String)> {
    if !(rms.is_finite() && rms >= 0.0) {
        return Err((format!("{at}.rms"), format!("{rms} is not a finite, non-negative RMS")));
    }
    for (name, v) in [("rvec", p.rvec), ("tvec", p.tvec)] {
        if v.iter().any(|x| !x.is_finite()) {
            return Err((format!("{at}.{name}"), format!("{v:?} has a non-finite component")));
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Reading.

/// Reads and validates a calibration file.
pub fn read(path: impl AsRef<Path>) -> Result<CalibrationFile, CalibFileError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|e| CalibFileError {
        path: path.into(),
        line: None,
        field: String::new(),
        message: format!("cannot read: {e}"),
    })?;
    parse(&text, path)
}

/// Parses a calibration file's text; `path` is only used in errors.
pub fn parse(text: &str, path: &Path) -> Result<CalibrationFile, CalibFileError> {
    let doc = Doc {
        path,
        newlines: text.bytes().enumerate().filter(|(_, b)| *b == b'\n').map(|(i, _)| i).collect(),
    };
    let root = DeTable::parse(text).map_err(|e| CalibFileError {
        path: path.into(),
        line: e.span().map(|s| doc.line(s.start)),
        field: String::new(),
        message: format!("not valid TOML: {}", e.message().trim()),
    })?;
    let root = Tbl { doc: &doc, t: root.get_ref(), name: String::new(), line: None };
    let format = root.str("format")?;
    if format.0 != FORMAT {
        return Err(doc.err(
            format.1,
            "format",
            format!("is {:?}, expected {FORMAT:?}: not a calibration file", format.0),
        ));
    }
    let version = root.int("version")?;
    if version.0 != VERSION {
        return Err(doc.err(
            version.1,
            "version",
            format!(
                "format version {} is not readable by this build, which reads version {VERSION}",
                version.0
            ),
        ));
    }
    root.only(&[
        "format",
        "version",
        "tool",
        "image",
        "intrinsics",
        "distortion",
        "board",
        "fit",
        "view",
        "reference",
    ])?;
    let tool = root.str("tool")?.0;

    let image = root.table("image")?;
    image.only(&["width", "height"])?;
    let size = |key: &str| -> Result<u32, CalibFileError> {
        let (v, line) = image.int(key)?;
        u32::try_from(v)
            .ok()
            .filter(|&v| v > 0)
            .ok_or_else(|| doc.err(line, &image.key(key), format!("{v} is not a positive size in pixels")))
    };
    let image_size = (size("width")?, size("height")?);

    let intr = root.table("intrinsics")?;
    intr.only(&["fx", "fy", "cx", "cy"])?;
    let dist = root.table("distortion")?;
    dist.only(&["k1", "k2", "p1", "p2", "k3"])?;
    let focal = |key: &str| -> Result<f64, CalibFileError> {
        let (v, line) = intr.float(key)?;
        if v > 0.0 {
            Ok(v)
        } else {
            Err(doc.err(line, &intr.key(key), format!("{v} is not a positive focal length in pixels")))
        }
    };
    let intrinsics = Intrinsics {
        fx: focal("fx")?,
        fy: focal("fy")?,
        cx: intr.float("cx")?.0,
        cy: intr.float("cy")?.0,
        k1: dist.float("k1")?.0,
        k2: dist.float("k2")?.0,
        p1: dist.float("p1")?.0,
        p2: dist.float("p2")?.0,
        k3: dist.float("k3")?.0,
    };

    let board_t = root.table("board")?;
    board_t.only(&["cols", "rows", "square", "unit"])?;
    let board = board_spec(&board_t)?;

    let fit = root.table("fit")?;
    fit.only(&["rms", "skipped"])?;
    let rms = fit.rms("rms")?;
    let skipped = fit.strings("skipped")?;

    let mut views = Vec::new();
    if let Some(list) = root.opt_array("view")? {
        for (i, item) in list.iter().enumerate() {
            let name = format!("view[{i}]");
            let t = root.array_table(item, &name)?;
            t.only(&["file", "rms", "rvec", "tvec"])?;
            views.push(View { file: t.str("file")?.0, rms: t.rms("rms")?, pose: t.pose()? });
        }
    }

    let reference = match root.opt_table("reference")? {
        None => None,
        Some(t) => {
            t.only(&["file", "cols", "rows", "square", "unit", "rms", "rvec", "tvec"])?;
            Some(Reference {
                file: t.str("file")?.0,
                board: board_spec(&t)?,
                rms: t.rms("rms")?,
                pose: t.pose()?,
            })
        }
    };
    Ok(CalibrationFile { tool, image_size, intrinsics, board, rms, views, skipped, reference })
}

fn board_spec(t: &Tbl<'_, '_, '_>) -> Result<BoardSpec, CalibFileError> {
    let count = |key: &str| -> Result<usize, CalibFileError> {
        let (v, line) = t.int(key)?;
        usize::try_from(v)
            .ok()
            .filter(|&v| v >= 2)
            .ok_or_else(|| t.doc.err(line, &t.key(key), format!("{v} inner corners: need at least 2")))
    };
    let (square, line) = t.float("square")?;
    if square <= 0.0 {
        return Err(t.doc.err(line, &t.key("square"), format!("{square} is not a positive square size")));
    }
    Ok(BoardSpec { cols: count("cols")?, rows: count("rows")?, square, unit: t.str("unit")?.0 })
}

/// The text's line index and path, for errors.
struct Doc<'p> {
    path: &'p Path,
    newlines: Vec<usize>,
}

impl Doc<'_> {
    fn line(&self, offset: usize) -> usize {
        self.newlines.partition_point(|&nl| nl < offset) + 1
    }

    fn err(&self, line: Option<usize>, field: &str, message: String) -> CalibFileError {
        CalibFileError { path: self.path.into(), line, field: field.into(), message }
    }
}

/// A table being read: its dotted name and header line (for errors about missing keys).
struct Tbl<'d, 't, 'i> {
    doc: &'d Doc<'d>,
    t: &'t DeTable<'i>,
    name: String,
    line: Option<usize>,
}

type Value<'t, 'i> = &'t Spanned<DeValue<'i>>;

impl<'d, 't, 'i> Tbl<'d, 't, 'i> {
    fn key(&self, key: &str) -> String {
        if self.name.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.name)
        }
    }

    fn get(&self, key: &str) -> Option<(Value<'t, 'i>, usize)> {
        self.t.iter().find(|(k, _)| k.get_ref() == key).map(|(k, v)| (v, self.doc.line(k.span().start)))
    }

    fn need(&self, key: &str) -> Result<(Value<'t, 'i>, usize), CalibFileError> {
        self.get(key).ok_or_else(|| {
            let table =
                if self.name.is_empty() { "the file".to_string() } else { format!("[{}]", self.name) };
            self.doc.err(self.line, &self.key(key), format!("missing from {table}"))
        })
    }

    fn wrong(&self, key: &str, line: usize, v: &DeValue<'_>, want: &str) -> CalibFileError {
        self.doc.err(Some(line), &self.key(key), format!("expected {want}, found {}", v.type_str()))
    }

    /// Refuses keys not in `known`.
    fn only(&self, known: &[&str]) -> Result<(), CalibFileError> {
        for (k, _) in self.t.iter() {
            if !known.contains(&k.get_ref().as_ref()) {
                return Err(self.doc.err(
                    Some(self.doc.line(k.span().start)),
                    &self.key(k.get_ref()),
                    format!("unknown key (expected one of: {})", known.join(", ")),
                ));
            }
        }
        Ok(())
    }

    fn str(&self, key: &str) -> Result<(String, Option<usize>), CalibFileError> {
        let (v, line) = self.need(key)?;
        match v.get_ref() {
            DeValue::String(s) => Ok((s.to_string(), Some(line))),
            other => Err(self.wrong(key, line, other, "a string")),
        }
    }

    fn int(&self, key: &str) -> Result<(i64, Option<usize>), CalibFileError> {
        let (v, line) = self.need(key)?;
        match v.get_ref() {
            DeValue::Integer(i) => {
                let digits: String = i.as_str().chars().filter(|&c| c != '_').collect();
                i64::from_str_radix(&digits, i.radix()).map(|n| (n, Some(line))).map_err(|_| {
                    self.doc.err(Some(line), &self.key(key), format!("integer {i} out of range"))
                })
            }
            other => Err(self.wrong(key, line, other, "an integer")),
        }
    }

    /// A finite number (integer literals accepted).
    fn float(&self, key: &str) -> Result<(f64, Option<usize>), CalibFileError> {
        let (v, line) = self.need(key)?;
        let x = number(v.get_ref()).ok_or_else(|| self.wrong(key, line, v.get_ref(), "a number"))?;
        if !x.is_finite() {
            return Err(self.doc.err(Some(line), &self.key(key), format!("{x} is not finite")));
        }
        Ok((x, Some(line)))
    }

    fn rms(&self, key: &str) -> Result<f64, CalibFileError> {
        let (v, line) = self.float(key)?;
        if v < 0.0 {
            return Err(self.doc.err(line, &self.key(key), format!("{v} is not a valid RMS (negative)")));
        }
        Ok(v)
    }

    fn vec3(&self, key: &str) -> Result<[f64; 3], CalibFileError> {
        let (v, line) = self.need(key)?;
        let bad = || self.doc.err(Some(line), &self.key(key), "expected an array of 3 finite numbers".into());
        let a = v.get_ref().as_array().ok_or_else(bad)?;
        let xs: Vec<f64> = a.iter().filter_map(|e| number(e.get_ref())).filter(|x| x.is_finite()).collect();
        xs.try_into().map_err(|_| bad())
    }

    fn pose(&self) -> Result<Pose, CalibFileError> {
        Ok(Pose { rvec: self.vec3("rvec")?, tvec: self.vec3("tvec")? })
    }

    fn strings(&self, key: &str) -> Result<Vec<String>, CalibFileError> {
        let (v, line) = self.need(key)?;
        let bad = || self.doc.err(Some(line), &self.key(key), "expected an array of strings".into());
        let a = v.get_ref().as_array().ok_or_else(bad)?;
        a.iter().map(|e| e.get_ref().as_str().map(str::to_string).ok_or_else(bad)).collect()
    }

    fn table(&self, key: &str) -> Result<Tbl<'d, 't, 'i>, CalibFileError> {
        self.opt_table(key)?
            .ok_or_else(|| self.doc.err(None, &self.key(key), format!("missing table [{}]", self.key(key))))
    }

    fn opt_table(&self, key: &str) -> Result<Option<Tbl<'d, 't, 'i>>, CalibFileError> {
        let Some((v, line)) = self.get(key) else { return Ok(None) };
        match v.get_ref() {
            DeValue::Table(t) => Ok(Some(Tbl { doc: self.doc, t, name: self.key(key), line: Some(line) })),
            other => Err(self.wrong(key, line, other, "a table")),
        }
    }

    fn opt_array(&self, key: &str) -> Result<Option<&'t DeArray<'i>>, CalibFileError> {
        let Some((v, line)) = self.get(key) else { return Ok(None) };
        match v.get_ref() {
            DeValue::Array(a) => Ok(Some(a)),
            other => Err(self.wrong(key, line, other, "an array of tables ([[view]])")),
        }
    }

    fn array_table(&self, item: Value<'t, 'i>, name: &str) -> Result<Tbl<'d, 't, 'i>, CalibFileError> {
        let line = self.doc.line(item.span().start);
        match item.get_ref() {
            DeValue::Table(t) => Ok(Tbl { doc: self.doc, t, name: name.into(), line: Some(line) }),
            other => {
                Err(self.doc.err(Some(line), name, format!("expected a table, found {}", other.type_str())))
            }
        }
    }
}

/// A TOML integer or float as `f64` (`inf`/`nan` come back non-finite for the caller to refuse).
fn number(v: &DeValue<'_>) -> Option<f64> {
    match v {
        DeValue::Integer(i) => {
            let digits: String = i.as_str().chars().filter(|&c| c != '_').collect();
            i64::from_str_radix(&digits, i.radix()).ok().map(|n| n as f64)
        }
        DeValue::Float(f) => {
            let s: String = f.as_str().chars().filter(|&c| c != '_').collect();
            match s.trim_start_matches(['+', '-']) {
                "inf" => Some(f64::INFINITY),
                "nan" => Some(f64::NAN),
                _ => s.parse().ok(),
            }
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> CalibrationFile {
        CalibrationFile {
            tool: "test \"tool\" 1.0".into(),
            image_size: (640, 480),
            intrinsics: Intrinsics {
                fx: 532.953770064904,
                fy: 533.0531814466676,
                cx: 342.0970353261548,
                cy: 234.08421136772006,
                k1: -0.28470050479360726,
                k2: 0.05706697610737325,
                p1: 0.0011031813633046294,
                p2: -1.034340593152007e-4,
                k3: 0.09919934812847385,
            },
            board: BoardSpec { cols: 9, rows: 6, square: 25.0, unit: "mm".into() },
            rms: 0.1787,
            views: vec![
                View {
                    file: "a/left01.jpg".into(),
                    rms: 0.15,
                    pose: Pose { rvec: [0.1, -0.2, 3.0], tvec: [-100.0, 50.5, 1e-20] },
                },
                View {
                    file: "dir with space/ü.png".into(),
                    rms: 0.2,
                    pose: Pose { rvec: [0.0; 3], tvec: [1.0, 2.0, 500.0] },
                },
            ],
            skipped: vec!["blank.png".into()],
            reference: Some(Reference {
                file: "plane.png".into(),
                board: BoardSpec { cols: 7, rows: 5, square: 30.0, unit: "mm".into() },
                rms: 0.1,
                pose: Pose { rvec: [2.9, 0.1, -0.05], tvec: [-90.0, 60.0, 700.0] },
            }),
        }
    }

    #[test]
    fn round_trips_exactly_and_deterministically() {
        let c = sample();
        let text = to_toml(&c).unwrap();
        assert_eq!(parse(&text, Path::new("x.toml")).unwrap(), c);
        assert_eq!(to_toml(&c).unwrap(), text);
        let none = CalibrationFile { reference: None, views: vec![], skipped: vec![], ..c };
        assert_eq!(parse(&to_toml(&none).unwrap(), Path::new("x.toml")).unwrap(), none);
    }

    /// Edits one line of a valid file and returns the error's `file:line: field: message`.
    fn error_after(from: &str, to: &str) -> String {
        let text = to_toml(&sample()).unwrap();
        assert!(text.contains(from), "{from:?} not in\n{text}");
        let text = text.replacen(from, to, 1);
        parse(&text, Path::new("cam.toml")).unwrap_err().to_string()
    }

    fn line_of(text: &str, needle: &str) -> usize {
        text.lines().position(|l| l.starts_with(needle)).unwrap() + 1
    }

    #[test]
    fn errors_name_file_line_and_field() {
        let text = to_toml(&sample()).unwrap();
        let fx = line_of(&text, "fx = ");
        assert_eq!(
            error_after("fx = 532.953770064904", "fx = -5.0"),
            format!("cam.toml:{fx}: intrinsics.fx: -5 is not a positive focal length in pixels")
        );
        assert_eq!(
            error_after("fx = 532.953770064904", "fx = nan"),
            format!("cam.toml:{fx}: intrinsics.fx: NaN is not finite")
        );
        assert_eq!(
            error_after("fx = 532.953770064904", "fx = \"big\""),
            format!("cam.toml:{fx}: intrinsics.fx: expected a number, found string")
        );
        assert_eq!(
            error_after("fx = 532.953770064904", "fz = 1.0"),
            format!("cam.toml:{fx}: intrinsics.fz: unknown key (expected one of: fx, fy, cx, cy)")
        );
        // A missing key points at its table's header.
        let header = line_of(&text, "[distortion]");
        assert_eq!(
            error_after("k2 = 0.05706697610737325\n", ""),
            format!("cam.toml:{header}: distortion.k2: missing from [distortion]")
        );
        let version = line_of(&text, "version");
        assert_eq!(
            error_after("version = 1", "version = 2"),
            format!("cam.toml:{version}: version: format version 2 is not readable by this build, which reads version 1")
        );
        // Second view's rvec.
        let rvec = text.lines().enumerate().filter(|(_, l)| l.starts_with("rvec")).nth(1).unwrap().0 + 1;
        assert_eq!(
            error_after("rvec = [0.0, 0.0, 0.0]", "rvec = [0.0, 0.0]"),
            format!("cam.toml:{rvec}: view[1].rvec: expected an array of 3 finite numbers")
        );
        assert_eq!(
            error_after("cols = 9", "cols = 1"),
            format!("cam.toml:{}: board.cols: 1 inner corners: need at least 2", line_of(&text, "cols = 9"))
        );
        assert!(error_after("[image]", "[image")
            .starts_with(&format!("cam.toml:{}: not valid TOML", line_of(&text, "[image]"))));
        assert!(error_after("format = \"lightrig-calibration\"", "format = \"other\"")
            .contains("format: is \"other\""));
        let missing =
            parse("format = \"lightrig-calibration\"\nversion = 1\ntool = \"t\"\n", Path::new("cam.toml"))
                .unwrap_err();
        assert_eq!(missing.to_string(), "cam.toml: image: missing table [image]");
        let unreadable = read("/nonexistent/cam.toml").unwrap_err().to_string();
        assert!(unreadable.starts_with("/nonexistent/cam.toml: cannot read: "), "{unreadable}");
    }

    #[test]
    fn refuses_to_write_what_it_would_not_read() {
        let mut c = sample();
        c.views[1].pose.tvec[2] = f64::NAN;
        assert_eq!(to_toml(&c).unwrap_err().0, "view[1].tvec");
        let dir = std::env::temp_dir().join(format!("lightrig-calib-file-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = write(dir.join("c.toml"), &c).unwrap_err();
        assert!(
            e.to_string()
                .ends_with("c.toml: view[1].tvec: [1.0, 2.0, NaN] has a non-finite component; not written"),
            "{e}"
        );
        assert!(!dir.join("c.toml").exists());
        write(dir.join("c.toml"), &sample()).unwrap();
        assert_eq!(read(dir.join("c.toml")).unwrap(), sample());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
