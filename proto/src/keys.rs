//! Key expressions. Every key ebmpc uses is built here, never spelled inline elsewhere.
//!
//! ```text
//! {prefix}/runs/{run}/agents/{agent}/obs     agent → planner   observations
//! {prefix}/runs/{run}/agents/{agent}/act     planner → agent   actions
//! {prefix}/runs/{run}/agents/{agent}/error   planner → agent   errors about what the agent sent
//! {prefix}/runs/{run}/attach                 queryable         attach an agent to a run
//! {prefix}/runs/{run}/events                 planner → all     training, model updates, episodes
//! {prefix}/runs/{run}/events/json            planner → all     the same events in JSON
//! {prefix}/planners/{id}/status              queryable         JSON status of a planner
//! {prefix}/planners/{id}/fleet               queryable         JSON pinning rules of a planner
//! {prefix}/alive/planners/{id}               liveliness token of a planner
//! {prefix}/alive/runs/{run}/agents/{agent}   liveliness token of an agent
//! {prefix}/alive/leases/{run}/{epoch}/{id}   liveliness token: planner `id` owns `run` at `epoch`
//! ```

use crate::codec::Encoding;

/// The default key prefix.
pub const DEFAULT_PREFIX: &str = "ebmpc";

/// A name that cannot be a run, agent or planner id. It holds the name as it may be shown:
/// at most [`SHOWN_NAME_CHARS`] characters, escaped, with the full length when cut, so that a
/// hostile name is never echoed whole into replies and logs.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "invalid name {0}: use 1-64 characters from letters, digits, '-', '_' and '.' (no '/', '*', '$', '?', '#')"
)]
pub struct InvalidName(pub String);

/// Characters of a refused name that an error shows.
pub const SHOWN_NAME_CHARS: usize = 32;

impl InvalidName {
    fn of(name: &str) -> Self {
        let shown: String = name.chars().take(SHOWN_NAME_CHARS).collect();
        let shown = shown.escape_debug();
        if name.chars().count() > SHOWN_NAME_CHARS {
            Self(format!("`{shown}…` ({} bytes)", name.len()))
        } else {
            Self(format!("`{shown}`"))
        }
    }
}

/// Checks a run, agent or planner name: it becomes one chunk of a key expression.
pub fn validate_name(name: &str) -> Result<(), InvalidName> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        && name != "."
        && name != "..";
    if ok {
        Ok(())
    } else {
        Err(InvalidName::of(name))
    }
}

/// The key builder for one prefix.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Keys {
    prefix: String,
}

impl Default for Keys {
    fn default() -> Self {
        Self {
            prefix: DEFAULT_PREFIX.to_string(),
        }
    }
}

/// Which agent-level key a sample arrived on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AgentChannel {
    Obs,
    Act,
    Error,
}

impl AgentChannel {
    fn suffix(self) -> &'static str {
        match self {
            AgentChannel::Obs => "obs",
            AgentChannel::Act => "act",
            AgentChannel::Error => "error",
        }
    }
}

impl Keys {
    /// Keys under `prefix` (no leading or trailing '/', e.g. `ebmpc` or `lab/ebmpc`).
    pub fn new(prefix: impl Into<String>) -> Self {
        let prefix = prefix.into().trim_matches('/').to_string();
        Self { prefix }
    }

    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    fn agent_key(&self, run: &str, agent: &str, channel: AgentChannel) -> String {
        format!(
            "{}/runs/{run}/agents/{agent}/{}",
            self.prefix,
            channel.suffix()
        )
    }

    pub fn obs(&self, run: &str, agent: &str) -> String {
        self.agent_key(run, agent, AgentChannel::Obs)
    }

    pub fn act(&self, run: &str, agent: &str) -> String {
        self.agent_key(run, agent, AgentChannel::Act)
    }

    pub fn error(&self, run: &str, agent: &str) -> String {
        self.agent_key(run, agent, AgentChannel::Error)
    }

    pub fn attach(&self, run: &str) -> String {
        format!("{}/runs/{run}/attach", self.prefix)
    }

    /// Where a run's events are published in `encoding`. Events are broadcast, so they cannot
    /// follow one receiver's encoding: the planner publishes each event in both, postcard on
    /// `…/events` (what ebmpc's own processes read) and JSON on `…/events/json` (controllers
    /// in other languages).
    pub fn events(&self, run: &str, encoding: Encoding) -> String {
        match encoding {
            Encoding::Postcard => format!("{}/runs/{run}/events", self.prefix),
            Encoding::Json => format!("{}/runs/{run}/events/json", self.prefix),
        }
    }

    pub fn planner_status(&self, planner: &str) -> String {
        format!("{}/planners/{planner}/status", self.prefix)
    }

    /// Where a planner serves its fleet profile (the run-name patterns it serves or refuses).
    pub fn planner_fleet(&self, planner: &str) -> String {
        format!("{}/planners/{planner}/fleet", self.prefix)
    }

    /// The liveliness token a planner holds while it owns `run` at ownership `epoch`.
    pub fn run_lease(&self, run: &str, epoch: u64, planner: &str) -> String {
        format!("{}/alive/leases/{run}/{epoch}/{planner}", self.prefix)
    }

    /// Every run's lease tokens.
    pub fn all_leases(&self) -> String {
        format!("{}/alive/leases/*/*/*", self.prefix)
    }

    /// `(run, epoch, planner)` of a lease token key.
    pub fn parse_lease<'k>(&self, key: &'k str) -> Option<(&'k str, u64, &'k str)> {
        let rest = key
            .strip_prefix(self.prefix.as_str())?
            .strip_prefix("/alive/leases/")?;
        let mut parts = rest.split('/');
        let run = parts.next()?;
        let epoch = parts.next()?.parse().ok()?;
        let planner = parts.next()?;
        parts.next().is_none().then_some((run, epoch, planner))
    }

    pub fn planner_alive(&self, planner: &str) -> String {
        format!("{}/alive/planners/{planner}", self.prefix)
    }

    pub fn agent_alive(&self, run: &str, agent: &str) -> String {
        format!("{}/alive/runs/{run}/agents/{agent}", self.prefix)
    }

    /// Every agent's observations, across all runs (what a planner subscribes to).
    pub fn all_obs(&self) -> String {
        self.obs("*", "*")
    }

    /// Every run's attach key (what a planner's queryable serves).
    pub fn all_attach(&self) -> String {
        self.attach("*")
    }

    /// Every planner's status key.
    pub fn all_planner_status(&self) -> String {
        self.planner_status("*")
    }

    /// Every planner's liveliness token.
    pub fn all_planners_alive(&self) -> String {
        self.planner_alive("*")
    }

    /// Every agent's liveliness token, across all runs.
    pub fn all_agents_alive(&self) -> String {
        self.agent_alive("*", "*")
    }

    /// `(run, agent)` of an agent-level key on `channel`, or `None` if the key is not one.
    /// Both chunks pass [`validate_name`]: a wildcard (`*`, `**`, `$*`) or any other chunk that
    /// is not a name never parses, so no reply is ever addressed to a key the sender chose
    /// beyond two checked names.
    pub fn parse_agent_key<'k>(
        &self,
        key: &'k str,
        channel: AgentChannel,
    ) -> Option<(&'k str, &'k str)> {
        let rest = key
            .strip_prefix(self.prefix.as_str())?
            .strip_prefix("/runs/")?;
        let mut parts = rest.split('/');
        let run = parts.next()?;
        (parts.next()? == "agents").then_some(())?;
        let agent = parts.next()?;
        (parts.next()? == channel.suffix() && parts.next().is_none()).then_some(())?;
        (validate_name(run).is_ok() && validate_name(agent).is_ok()).then_some((run, agent))
    }

    /// `(run, agent)` of an agent's liveliness token key.
    pub fn parse_agent_alive<'k>(&self, key: &'k str) -> Option<(&'k str, &'k str)> {
        let rest = key
            .strip_prefix(self.prefix.as_str())?
            .strip_prefix("/alive/runs/")?;
        let mut parts = rest.split('/');
        let run = parts.next()?;
        (parts.next()? == "agents").then_some(())?;
        let agent = parts.next()?;
        parts.next().is_none().then_some((run, agent))
    }

    /// The run of an attach key.
    pub fn parse_attach<'k>(&self, key: &'k str) -> Option<&'k str> {
        let rest = key
            .strip_prefix(self.prefix.as_str())?
            .strip_prefix("/runs/")?;
        let run = rest.strip_suffix("/attach")?;
        (!run.contains('/')).then_some(run)
    }

    /// The planner id of a planner liveliness key.
    pub fn parse_planner_alive<'k>(&self, key: &'k str) -> Option<&'k str> {
        let id = key
            .strip_prefix(self.prefix.as_str())?
            .strip_prefix("/alive/planners/")?;
        (!id.contains('/')).then_some(id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_round_trip() {
        let k = Keys::new("lab/ebmpc/");
        assert_eq!(k.obs("r1", "a-1"), "lab/ebmpc/runs/r1/agents/a-1/obs");
        assert_eq!(
            k.parse_agent_key(&k.obs("r1", "a-1"), AgentChannel::Obs),
            Some(("r1", "a-1"))
        );
        assert_eq!(
            k.parse_agent_key(&k.act("r1", "a-1"), AgentChannel::Obs),
            None
        );
        assert_eq!(
            k.parse_agent_key("lab/ebmpc/runs/r1/agents/a/obs/x", AgentChannel::Obs),
            None
        );
        assert_eq!(
            k.parse_agent_key("other/runs/r1/agents/a/obs", AgentChannel::Obs),
            None
        );
        for not_names in [
            "lab/ebmpc/runs/*/agents/*/obs",
            "lab/ebmpc/runs/r1/agents/*/obs",
            "lab/ebmpc/runs/**/agents/a/obs",
            "lab/ebmpc/runs/r$*/agents/a/obs",
            "lab/ebmpc/runs/r 1/agents/a/obs",
        ] {
            assert_eq!(k.parse_agent_key(not_names, AgentChannel::Obs), None);
        }
        assert_eq!(k.parse_attach(&k.attach("run.7")), Some("run.7"));
        assert_eq!(
            k.parse_agent_alive(&k.agent_alive("r", "a")),
            Some(("r", "a"))
        );
        assert_eq!(k.parse_planner_alive(&k.planner_alive("p1")), Some("p1"));
        assert_eq!(
            k.parse_lease(&k.run_lease("r.1", 7, "p1")),
            Some(("r.1", 7, "p1"))
        );
        assert_eq!(k.parse_lease("lab/ebmpc/alive/leases/r/x/p1"), None);
        assert_eq!(k.parse_lease("lab/ebmpc/alive/leases/r/1/p1/x"), None);
        assert_eq!(k.all_leases(), "lab/ebmpc/alive/leases/*/*/*");
        assert_eq!(k.planner_fleet("p1"), "lab/ebmpc/planners/p1/fleet");
        assert_eq!(k.all_obs(), "lab/ebmpc/runs/*/agents/*/obs");
        assert_eq!(k.events("r", Encoding::Postcard), "lab/ebmpc/runs/r/events");
        assert_eq!(
            k.events("r", Encoding::Json),
            "lab/ebmpc/runs/r/events/json"
        );
    }

    #[test]
    fn names_are_single_chunks() {
        for ok in ["run1", "cartpole-deen_s0", "a.b"] {
            validate_name(ok).unwrap();
        }
        for bad in ["", "a/b", "*", "$x", "a b", "..", &"x".repeat(65)] {
            assert!(validate_name(bad).is_err(), "{bad}");
        }
    }

    /// A refused name is shown cut to a few characters, escaped, with its length.
    #[test]
    fn refused_names_are_shown_cut_and_escaped() {
        let long = "x".repeat(100_000);
        let err = validate_name(&long).unwrap_err().to_string();
        assert!(err.len() < 200, "{err}");
        assert!(
            err.contains(&format!("`{}…` (100000 bytes)", "x".repeat(32))),
            "{err}"
        );
        let err = validate_name("bad\nname\u{1b}[31m")
            .unwrap_err()
            .to_string();
        assert!(!err.contains('\n') && !err.contains('\u{1b}'), "{err}");
        assert!(
            validate_name("ok/")
                .unwrap_err()
                .to_string()
                .contains("`ok/`")
        );
    }
}
