//! Method labels of an experiment: the planner's presets, and the same presets planned by iCEM.
//!
//! A label is either a preset name ([`planner_service::config::METHODS`]: `cem`, `cem+deen`,
//! …) or a CEM preset's name with `icem` in place of its leading `cem` (`icem`, `icem+dae`,
//! `icem+deen`): the same models, regulariser and training as that preset, planned by iCEM
//! (`optimizer = "icem"`) with the scale's iCEM search sizes ([`crate::scale`]). The runs then
//! attach with the CEM preset's name and the optimiser as an override, so the daemon needs no
//! preset of its own for them, and an experiment can put the paper's CEM and iCEM side by side
//! with one `--methods cem+deen,icem+deen`.

use planner_service::config::{METHODS, Preset, PresetError};
use planner_service::plan::Optimizer;
use proto::Builtin;

/// What a method label asks for.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Method {
    /// The preset the runs attach with.
    pub preset: String,
    /// The optimiser that plans (the preset's own unless the label says `icem`).
    pub optimizer: Optimizer,
}

impl Method {
    /// Parses a label: a preset name, or `icem…` for the `cem…` preset planned by iCEM.
    /// Refuses a name that is neither (with the known labels in the error).
    pub fn parse(task: Builtin, label: &str) -> Result<Self, PresetError> {
        let (preset, icem) = match label.strip_prefix("icem") {
            Some(rest) => (format!("cem{rest}"), true),
            None => (label.to_string(), false),
        };
        let paper = Preset::new(task.task(), Some(&preset)).map_err(|_| unknown(label))?;
        let optimizer = if icem {
            if paper.cem.optimizer != Optimizer::Cem {
                return Err(unknown(label));
            }
            Optimizer::Icem
        } else {
            paper.cem.optimizer
        };
        Ok(Method { preset, optimizer })
    }

    /// Whether the label replaced the preset's CEM by iCEM.
    pub fn is_icem(&self) -> bool {
        self.optimizer == Optimizer::Icem
    }
}

fn unknown(label: &str) -> PresetError {
    let icem: Vec<String> = METHODS
        .iter()
        .filter(|m| m.starts_with("cem"))
        .map(|m| format!("i{m}"))
        .collect();
    PresetError::InvalidOverride(format!(
        "unknown method `{label}` (known: {}, and iCEM in place of CEM: {})",
        METHODS.join(", "),
        icem.join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_keep_their_optimiser_and_icem_labels_name_the_cem_preset() {
        let m = Method::parse(Builtin::HalfCheetah, "cem+deen").unwrap();
        assert_eq!(
            (m.preset.as_str(), m.optimizer),
            ("cem+deen", Optimizer::Cem)
        );
        let m = Method::parse(Builtin::HalfCheetah, "icem+deen").unwrap();
        assert_eq!(
            (m.preset.as_str(), m.optimizer),
            ("cem+deen", Optimizer::Icem)
        );
        assert!(m.is_icem());
        let m = Method::parse(Builtin::Cartpole, "icem").unwrap();
        assert_eq!((m.preset.as_str(), m.optimizer), ("cem", Optimizer::Icem));
        let m = Method::parse(Builtin::Cartpole, "adam+dae").unwrap();
        assert_eq!(m.optimizer, Optimizer::Adam);
    }

    #[test]
    fn labels_that_name_no_cem_preset_are_refused() {
        for label in [
            "icem+pets",
            "iadam+dae",
            "icemx",
            "ipets",
            "",
            "icem+",
            "ICEM",
        ] {
            let err = Method::parse(Builtin::Cartpole, label).unwrap_err();
            assert!(err.to_string().contains("icem+deen"), "{label}: {err}");
        }
    }
}
