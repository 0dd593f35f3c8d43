//! The PCA-steered bispectral acquisition (thesis §4.5), decided inside one session: once the
//! dense light angles are in, the host runs the PCA on them and chooses the wavelength pairs
//! the other angles take. The choice is made once and kept in the session
//! ([`CHOICE_FILE`]), so that `lightrig resume` and the fit see the same pairs.
//!
//! The PCA needs the samples scaled like the fit's: the Spectralon session named by the rig
//! file's `[plan.fit] spectralon` (relative to the session directory) must exist by then.

use std::path::Path;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::fit::brrdf;
use crate::plan::brrdf::{Chooser, Pair};
use crate::rigfile::RigFile;

/// The choice, in the session directory.
pub const CHOICE_FILE: &str = "pca-choice.json";

/// What [`CHOICE_FILE`] holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Choice {
    /// The chosen `(excitation, emission)` pairs, nm, in the order the plan takes them.
    pub pairs: Vec<[u16; 2]>,
    /// The light angles of the samples the PCA saw, degrees.
    pub from_light_deg: Vec<f64>,
    /// `cond(R)` of the choice (saturated PCA).
    pub cond: f64,
}

impl Choice {
    /// The session's choice, if made.
    pub fn load(session: &Path) -> Result<Option<Choice>, String> {
        let p = session.join(CHOICE_FILE);
        match std::fs::read_to_string(&p) {
            Ok(t) => serde_json::from_str(&t).map(Some).map_err(|e| format!("{}: {e}", p.display())),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(format!("{}: {e}", p.display())),
        }
    }

    /// Writes the choice into the session (a temporary file renamed over, then synced).
    pub fn save(&self, session: &Path) -> Result<(), String> {
        let p = session.join(CHOICE_FILE);
        let tmp = session.join(format!("{CHOICE_FILE}.tmp"));
        let json = serde_json::to_string_pretty(self).map_err(|e| e.to_string())? + "\n";
        let write = || -> std::io::Result<()> {
            use std::io::Write;
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(json.as_bytes())?;
            f.sync_all()?;
            std::fs::rename(&tmp, &p)?;
            std::fs::File::open(session)?.sync_all()
        };
        write().map_err(|e| format!("{}: {e}", p.display()))
    }
}

/// The plan's chooser for `rig`: the session's saved choice, or (the first time) the PCA of its
/// dense steps through [`brrdf::choose`], saved. `all` are the plan's pairs (with their wheel
/// slots); `select` how many to choose.
pub fn chooser(rig: RigFile, all: Vec<Pair>, select: usize) -> Chooser {
    Arc::new(move |dir: &Path| {
        let choice = match Choice::load(dir)? {
            Some(c) => c,
            None => {
                let spec = brrdf::FitSpec::from_rig(&rig).map_err(|e| e.to_string())?;
                let cal = spec.spectralon.as_ref().map(|p| dir.join(p)).ok_or_else(|| {
                    format!(
                        "{}: the PCA-steered plan needs the Spectralon session before its sparse angles: \
                         name it in [plan.fit] spectralon (relative to the session directory)",
                        rig.path.display()
                    )
                })?;
                let c = brrdf::choose(dir, &cal, select).map_err(|e| e.to_string())?;
                c.save(dir)?;
                c
            }
        };
        choice
            .pairs
            .iter()
            .map(|&[ex, em]| {
                all.iter().find(|p| p.excitation == ex && p.emission == em).copied().ok_or_else(|| {
                    format!(
                        "{}: the chosen pair {ex}→{em} nm is not one of the plan's pairs",
                        dir.join(CHOICE_FILE).display()
                    )
                })
            })
            .collect()
    })
}
