//! The planner configuration of the end-to-end tests: two-layer networks and a small CEM
//! search, so that a daemon trains and plans within a test's timeouts on a loaded 2-core
//! machine. The tests check plumbing, not learning; what differs between them (sizes, the
//! planner id, limits, a Zenoh file) is a parameter of one template, so a change to the
//! configuration format is made once.

/// Network sizes, training epochs and CEM search size of a test planner (every network, the
/// reward model of a task whose reward is learned too, has two hidden layers of `hidden_size`
/// units; they train for `epochs`; CEM runs two iterations).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sizes {
    pub hidden_size: u32,
    pub epochs: u32,
    pub population: u32,
    pub elites: u32,
    pub horizon: u32,
}

impl Sizes {
    /// For a real MuJoCo task through sim-bridge, or a controller that plays whole episodes.
    pub const SMALL: Self = Self {
        hidden_size: 32,
        epochs: 5,
        population: 40,
        elites: 5,
        horizon: 8,
    };

    /// For scripted agents on the toy system, where many steps are played in one test.
    pub const TINY: Self = Self {
        hidden_size: 16,
        epochs: 3,
        population: 20,
        elites: 4,
        horizon: 5,
    };
}

/// A `planner-service serve --config` file for a test planner.
#[derive(Clone, Debug)]
pub struct PlannerConfig {
    planner_id: String,
    sizes: Sizes,
    exploration_episodes: Option<u32>,
    top_level: Vec<String>,
    /// The planner's `[fleet]` table when it is a member of a fleet.
    fleet: Option<String>,
}

impl PlannerConfig {
    /// A planner `planner_id` with networks and search of `sizes`; exploration as in the
    /// preset an agent asks for.
    pub fn new(planner_id: &str, sizes: Sizes) -> Self {
        Self {
            planner_id: planner_id.to_string(),
            sizes,
            exploration_episodes: None,
            top_level: Vec::new(),
            fleet: None,
        }
    }

    /// Makes the planner a member of a fleet whose ownership lives in the etcd at `endpoint`
    /// (a `[fleet]` table, lease of `ttl_seconds`; no pins: every run may be placed on it).
    /// Without it a planner is alone and needs no etcd.
    pub fn in_fleet(mut self, endpoint: &str, ttl_seconds: u64) -> Self {
        self.fleet = Some(crate::etcd::fleet_toml(endpoint, ttl_seconds));
        self
    }

    /// Overrides every run's random exploration to `episodes` episodes.
    pub fn exploration_episodes(mut self, episodes: u32) -> Self {
        self.exploration_episodes = Some(episodes);
        self
    }

    /// Adds a top-level TOML line, e.g. `max_runs = 2` or `zenoh_config = "/path"`.
    pub fn line(mut self, toml: impl Into<String>) -> Self {
        self.top_level.push(toml.into());
        self
    }

    /// The configuration file's text.
    pub fn toml(&self) -> String {
        let Sizes {
            hidden_size,
            epochs,
            population,
            elites,
            horizon,
        } = self.sizes;
        let id = &self.planner_id;
        let top: String = self.top_level.iter().map(|l| format!("{l}\n")).collect();
        let exploration = self
            .exploration_episodes
            .map(|n| format!("exploration_episodes = {n}\n"))
            .unwrap_or_default();
        let fleet = self.fleet.as_deref().unwrap_or_default();
        format!(
            r#"planner_id = "{id}"
{top}{fleet}[overrides]
dynamics_hidden_layers = 2
dynamics_hidden_size = {hidden_size}
dynamics_epochs = {epochs}
energy_hidden_layers = 2
energy_hidden_size = {hidden_size}
energy_epochs = {epochs}
reward_hidden_layers = 2
reward_hidden_size = {hidden_size}
population = {population}
elites = {elites}
horizon = {horizon}
cem_iterations = 2
{exploration}"#
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::TempDir;
    use planner_service::config::ServiceConfig;
    use proto::PlannerOverrides;

    /// The text is what the daemon reads: it loads, and every value lands where it should.
    #[test]
    fn the_daemon_reads_every_setting() {
        let dir = TempDir::new("config");
        let path = dir.path().join("planner.toml");
        let config = PlannerConfig::new("cfg-test", Sizes::TINY)
            .exploration_episodes(1)
            .line("max_runs = 2")
            .line("max_agents_per_run = 3");
        std::fs::write(&path, config.toml()).unwrap();
        let loaded = ServiceConfig::load(&path).unwrap();
        assert_eq!(loaded.planner_id, "cfg-test");
        assert_eq!((loaded.max_runs, loaded.max_agents_per_run), (2, 3));
        assert_eq!(
            loaded.overrides,
            PlannerOverrides {
                dynamics_hidden_layers: Some(2),
                dynamics_hidden_size: Some(16),
                dynamics_epochs: Some(3),
                energy_hidden_layers: Some(2),
                energy_hidden_size: Some(16),
                energy_epochs: Some(3),
                reward_hidden_layers: Some(2),
                reward_hidden_size: Some(16),
                population: Some(20),
                elites: Some(4),
                horizon: Some(5),
                cem_iterations: Some(2),
                exploration_episodes: Some(1),
                ..Default::default()
            }
        );

        std::fs::write(&path, PlannerConfig::new("small", Sizes::SMALL).toml()).unwrap();
        let loaded = ServiceConfig::load(&path).unwrap();
        let o = &loaded.overrides;
        assert_eq!(
            (o.dynamics_hidden_size, o.energy_epochs, o.population),
            (Some(32), Some(5), Some(40))
        );
        assert_eq!(
            (o.elites, o.horizon, o.exploration_episodes),
            (Some(5), Some(8), None)
        );
    }
}
