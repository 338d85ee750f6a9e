//! Configuration of the planner daemon: the service settings (TOML file, overridable from the
//! command line) and the per-task presets of the paper's Table 2.

mod limits;
mod pins;
mod preset;

pub use limits::{Cost, InvalidLimits, LimitExceeded, Limits};
pub use pins::{Pins, PinsError};
pub use preset::{DEFAULT_METHOD, METHODS, Preset, PresetError};
pub use proto::EpochSchedule;

use proto::{TaskCatalog, TaskSpec};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The daemon's configuration file (`planner-service serve --config FILE`).
///
/// Every field has a default, so an empty file is a valid configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct ServiceConfig {
    /// This planner's id: its status key and liveliness token carry it.
    pub planner_id: String,
    /// Key prefix shared with the agents.
    pub prefix: String,
    /// Zenoh endpoints to listen on.
    pub listen: Vec<String>,
    /// Zenoh endpoints (peers or a router) to connect to.
    pub connect: Vec<String>,
    /// A zenoh configuration file (JSON5) to start from; endpoints above are applied on top.
    pub zenoh_config: Option<PathBuf>,
    /// Where runs keep their replay buffers and models.
    pub data_dir: PathBuf,
    /// Most runs this daemon hosts at once: further attaches to new runs are refused, and a
    /// restart opens at most this many stored runs (the newest first; also only while the
    /// open runs' replay is below `[storage] max_total_replay_bytes`). The others stay on
    /// disk untouched, listed by `status` as dormant, refused at attach with the budget's name.
    pub max_runs: usize,
    /// Most agents attached to one run at once.
    pub max_agents_per_run: usize,
    /// Presets agents may ask for (empty: all).
    pub allowed_presets: Vec<String>,
    /// Overrides applied to every run's preset before the agent's own (e.g. smaller networks
    /// for a quick test), keyed like the attach message's overrides.
    pub overrides: proto::PlannerOverrides,
    /// Membership of a fleet of planners (`[fleet]`: etcd endpoints, lease, pins). Absent: a
    /// single daemon that owns every run in its data directory and needs no etcd.
    pub fleet: Option<FleetConfig>,
    /// The least share of the cores a retraining gets while plans leave it no idle time, in
    /// (0, 1]: plans come first, but a retraining that finds plans running before a
    /// minibatch waits at most `(1 − share) / share` times as long as its last minibatch
    /// took, then runs one minibatch while plans wait. So under continuous planning a
    /// retraining takes about `share` of the time (and plans the rest) instead of waiting
    /// for ever. `status` shows when a retraining is starving.
    pub retraining_share: f64,
    /// Bounds on everything a client chooses (`[limits]`).
    pub limits: Limits,
    /// How runs keep their data on disk (`[storage]`).
    pub storage: StorageConfig,
    /// The Prometheus endpoint (`[metrics]`).
    pub metrics: MetricsConfig,
    /// Tasks this daemon knows besides the built-in five (`[tasks.NAME]`, a task spec each;
    /// the table's key is the name).
    pub tasks: BTreeMap<String, TaskSpec>,
    /// A folder of task specs, one `NAME.toml` or `NAME.json` file each, read at start.
    pub tasks_dir: Option<PathBuf>,
}

/// `[metrics]`: where the Prometheus text endpoint listens.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MetricsConfig {
    /// Address of the endpoint (`GET /metrics`), e.g. `127.0.0.1:9464`. Absent: no endpoint.
    /// It carries no authentication: keep it on loopback, or behind a proxy that has some.
    pub listen: Option<std::net::SocketAddr>,
}

/// `[fleet]`: this planner is one of several sharing a data directory, and etcd decides which
/// of them owns each run (see `crate::fleet`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FleetConfig {
    /// The etcd cluster's client endpoints, e.g. `["http://10.0.0.5:2379"]` (at least one).
    pub etcd: Vec<String>,
    /// Seconds an etcd lease lives without renewal: how long a dead owner's runs wait before
    /// another planner may take them, and the bound on how long a planner cut off from etcd
    /// may keep acknowledging (it stops a fifth of this, at least 1 s, earlier).
    #[serde(default = "FleetConfig::default_lease_ttl")]
    pub lease_ttl_seconds: u64,
    /// Run-name patterns this planner serves (empty: all): a preference, see `crate::fleet`.
    #[serde(default)]
    pub serve: Vec<String>,
    /// Run-name patterns this planner never serves, whatever `serve` says.
    #[serde(default)]
    pub refuse: Vec<String>,
}

impl FleetConfig {
    fn default_lease_ttl() -> u64 {
        10
    }

    /// Shortest and longest lease accepted: below 3 s a renewal has no room for a retry;
    /// beyond 5 minutes a dead owner's runs wait too long.
    pub const LEASE_TTL_SECONDS: std::ops::RangeInclusive<u64> = 3..=300;

    /// The pins: `serve` and `refuse`.
    pub fn pins(&self) -> Pins {
        Pins {
            serve: self.serve.clone(),
            refuse: self.refuse.clone(),
        }
    }

    fn validate(&self) -> Result<(), ConfigError> {
        self.pins().validate()?;
        if self.etcd.is_empty() {
            return Err(ConfigError::Fleet(
                "`etcd` must list at least one endpoint (a fleet's ownership lives in etcd)".into(),
            ));
        }
        if !Self::LEASE_TTL_SECONDS.contains(&self.lease_ttl_seconds) {
            return Err(ConfigError::Fleet(format!(
                "lease_ttl_seconds = {} is outside {}..={}",
                self.lease_ttl_seconds,
                Self::LEASE_TTL_SECONDS.start(),
                Self::LEASE_TTL_SECONDS.end()
            )));
        }
        Ok(())
    }
}

/// `[storage]`: how much of its experience a run keeps.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct StorageConfig {
    /// Most transitions a run's replay buffer keeps; beyond it the transitions of the oldest
    /// finished episodes are evicted whole, from memory at once and from the log by
    /// compaction. Absent: unbounded (the paper's protocol trains on everything), up to the
    /// byte budgets below.
    pub replay_capacity: Option<usize>,
    /// Most bytes one run's replay log may hold (its replay in memory is about as large): at
    /// the budget the run refuses every observation that would store something, with an error
    /// naming this setting. Default 1 GiB (over 5,000 half-cheetah episodes).
    pub max_run_replay_bytes: u64,
    /// Most bytes the replay logs of all open runs may hold together: at the budget every run
    /// refuses what it would store, with an error naming this setting. Default 8 GiB.
    pub max_total_replay_bytes: u64,
    /// Acknowledge a step only once it is on stable storage (one `fdatasync` per batch of
    /// appends, shared by the agents storing at the same moment), so a host's power loss
    /// loses nothing acknowledged. Absent: on in a fleet (`[fleet]`), off for a single daemon
    /// (which syncs at every episode end and hands every step to the OS before answering).
    pub sync_every_step: Option<bool>,
}

impl Default for StorageConfig {
    fn default() -> Self {
        Self {
            replay_capacity: None,
            max_run_replay_bytes: 1 << 30,
            max_total_replay_bytes: 8 << 30,
            sync_every_step: None,
        }
    }
}

impl ServiceConfig {
    /// Whether steps are synced to stable storage before they are acknowledged.
    pub fn sync_every_step(&self) -> bool {
        self.storage.sync_every_step.unwrap_or(self.fleet.is_some())
    }
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            planner_id: "planner".into(),
            prefix: proto::keys::DEFAULT_PREFIX.into(),
            listen: Vec::new(),
            connect: Vec::new(),
            zenoh_config: None,
            data_dir: PathBuf::from("var/ebmpc"),
            max_runs: 64,
            max_agents_per_run: 16,
            allowed_presets: Vec::new(),
            overrides: proto::PlannerOverrides::default(),
            fleet: None,
            retraining_share: crate::sched::DEFAULT_TRAINING_SHARE,
            limits: Limits::default(),
            storage: StorageConfig::default(),
            metrics: MetricsConfig::default(),
            tasks: BTreeMap::new(),
            tasks_dir: None,
        }
    }
}

/// The JSON schema of the configuration file: every key with its doc comment and default.
/// `docs/configuration.md`'s reference of the TOML keys is generated from it.
pub fn schema() -> serde_json::Value {
    proto::schema::schema_of::<ServiceConfig>()
}

/// A configuration file that could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("invalid config file {path}: {source}")]
    Parse {
        path: PathBuf,
        source: Box<toml::de::Error>,
    },
    #[error("invalid planner id: {0}")]
    PlannerId(#[from] proto::keys::InvalidName),
    #[error("[fleet]: {0}")]
    Pins(#[from] PinsError),
    #[error("[fleet]: {0}")]
    Fleet(String),
    #[error(transparent)]
    Limits(#[from] InvalidLimits),
    #[error("retraining_share = {0} must be above 0 and at most 1")]
    RetrainingShare(f64),
    #[error(transparent)]
    Tasks(#[from] proto::task::CatalogError),
}

impl ServiceConfig {
    /// Reads a TOML configuration file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.into(),
            source,
        })?;
        let config: ServiceConfig = toml::from_str(&text).map_err(|source| ConfigError::Parse {
            path: path.into(),
            source: Box::new(source),
        })?;
        config.validate()?;
        Ok(config)
    }

    /// Checks what serde cannot, the declared tasks included.
    pub fn validate(&self) -> Result<(), ConfigError> {
        proto::validate_name(&self.planner_id)?;
        if let Some(fleet) = &self.fleet {
            fleet.validate()?;
        }
        self.limits.validate()?;
        if !(self.retraining_share > 0.0 && self.retraining_share <= 1.0) {
            return Err(ConfigError::RetrainingShare(self.retraining_share));
        }
        self.catalog()?;
        Ok(())
    }

    /// The tasks this daemon knows: the built-ins, `[tasks.NAME]` and the tasks folder, each
    /// declared task checked against `[limits]`; every `[limits.magnitudes.NAME]` must name one.
    pub fn catalog(&self) -> Result<TaskCatalog, ConfigError> {
        let bounds = self.limits.spec_bounds();
        let mut catalog = TaskCatalog::builtin();
        for (name, spec) in &self.tasks {
            catalog.declare(name, spec.clone(), &bounds)?;
        }
        if let Some(dir) = &self.tasks_dir {
            catalog.declare_folder(dir, &bounds)?;
        }
        for task in self.limits.magnitudes.keys() {
            catalog.get(task).map_err(InvalidLimits::from)?;
        }
        Ok(catalog)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_a_partial_file_over_defaults() {
        let config: ServiceConfig = toml::from_str(
            r#"
            planner_id = "lab-1"
            listen = ["tcp/127.0.0.1:7447"]
            max_runs = 4
            [overrides]
            population = 50
            inference_precision = "f32"
            [fleet]
            etcd = ["http://127.0.0.1:2379"]
            serve = ["ant-*"]
            "#,
        )
        .unwrap();
        let fleet = config.fleet.as_ref().unwrap();
        assert_eq!(fleet.serve, vec!["ant-*".to_string()]);
        assert!(fleet.refuse.is_empty());
        assert_eq!(fleet.lease_ttl_seconds, 10);
        assert!(ServiceConfig::default().fleet.is_none());
        let alone: ServiceConfig = toml::from_str("planner_id = \"solo\"").unwrap();
        assert_eq!(alone.fleet, None, "no [fleet]: a planner alone");
        config.validate().unwrap();
        assert_eq!(config.planner_id, "lab-1");
        assert_eq!(config.max_runs, 4);
        assert_eq!(config.overrides.population, Some(50));
        assert_eq!(
            config.overrides.inference_precision,
            Some(proto::InferencePrecision::F32)
        );
        assert_eq!(
            config.max_agents_per_run,
            ServiceConfig::default().max_agents_per_run
        );
    }

    #[test]
    fn a_storage_table_sets_the_replay_capacity() {
        let config: ServiceConfig = toml::from_str("[storage]\nreplay_capacity = 50000").unwrap();
        assert_eq!(config.storage.replay_capacity, Some(50_000));
        assert_eq!(ServiceConfig::default().storage.replay_capacity, None);
        assert!(toml::from_str::<ServiceConfig>("[storage]\ncapacity = 5").is_err());
    }

    #[test]
    fn rejects_unknown_keys() {
        assert!(toml::from_str::<ServiceConfig>("max_run = 3").is_err());
        assert!(toml::from_str::<ServiceConfig>("[fleet]\nserves = []").is_err());
    }

    #[test]
    fn rejects_bad_pins() {
        let config: ServiceConfig =
            toml::from_str("[fleet]\netcd = [\"http://e:2379\"]\nrefuse = [\"a/b\"]").unwrap();
        let err = config.validate().unwrap_err();
        assert!(
            err.to_string()
                .starts_with("[fleet]: invalid run-name pattern"),
            "{err}"
        );
        for bad in [
            "[fleet]\netcd = []",
            "[fleet]\netcd = [\"e\"]\nlease_ttl_seconds = 1",
        ] {
            let config: ServiceConfig = toml::from_str(bad).unwrap();
            assert!(config.validate().is_err(), "{bad}");
        }
    }

    /// The shipped example listens on loopback only, and its `[limits]` block states the
    /// defaults (so the file documents what an operator gets without it).
    #[test]
    fn the_shipped_config_listens_on_loopback_with_the_default_limits() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/planner.toml");
        let config = ServiceConfig::load(&path).unwrap();
        assert_eq!(config.listen, ["tcp/127.0.0.1:7447"]);
        assert_eq!(config.limits, Limits::default());
    }

    /// `[tasks.NAME]` declares a task by name; a bad one is refused at load, naming it.
    #[test]
    fn declared_tasks_join_the_catalog() {
        let config: ServiceConfig = toml::from_str(
            r#"
            [tasks.short-cartpole]
            obs_dim = 4
            act_dim = 1
            action_low = [-3.0]
            action_high = [3.0]
            episode_len = 50
            control_dt = 0.04
            reward = { builtin = "cartpole" }
            model = { declared = { angles = [1] } }
            [limits.magnitudes.short-cartpole]
            observation = 1e5
            reward = 10.0
            "#,
        )
        .unwrap();
        config.validate().unwrap();
        let catalog = config.catalog().unwrap();
        let task = catalog.get("short-cartpole").unwrap();
        assert_eq!((task.episode_len, task.state_feature_dim), (50, 5));
        assert_eq!(config.limits.magnitudes(task).observation, 1e5);
        assert!(catalog.get("ant").is_ok());

        let unknown: ServiceConfig =
            toml::from_str("[limits.magnitudes.walker]\nobservation = 1.0\nreward = 1.0").unwrap();
        let err = unknown.validate().unwrap_err().to_string();
        assert!(err.contains("unknown task `walker`"), "{err}");
        let mut too_big = config.clone();
        too_big.limits.max_obs_dim = 3;
        let err = too_big.validate().unwrap_err().to_string();
        assert!(err.contains("task short-cartpole: obs_dim = 4"), "{err}");
    }

    /// The own-system example of docs/own-system.md (`examples/tasks/balance-bot.toml`, a made-up robot)
    /// is a valid spec file: a tasks folder with it gives its task, formulas and all.
    #[test]
    fn the_example_robot_spec_joins_the_catalog() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/tasks");
        let config = ServiceConfig {
            tasks_dir: Some(dir),
            ..ServiceConfig::default()
        };
        config.validate().unwrap();
        let catalog = config.catalog().unwrap();
        let task = catalog.get("balance-bot").unwrap();
        assert_eq!((task.obs_dim, task.act_dim, task.episode_len), (6, 2, 1000));
        // The heading is seen as its sine and cosine: one feature more than the observation.
        assert_eq!(task.state_feature_dim, 7);
        let (upright, fallen) = ([0.0; 6], [0.9, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(task.reward(&upright, &[0.0, 0.0], &upright), 1.0);
        assert!(task.is_terminal(&fallen) && !task.is_terminal(&upright));
    }

    #[test]
    fn invalid_limits_are_refused_at_load() {
        let config: ServiceConfig = toml::from_str("[limits]\nmax_horizon = 0\n").unwrap();
        assert!(matches!(config.validate(), Err(ConfigError::Limits(_))));
        assert!(toml::from_str::<ServiceConfig>("[limits]\nmax_horizn = 3\n").is_err());
    }
}
