//! A real single-member etcd for tests of a fleet: started on free loopback ports with its data
//! in the test's directory, killed (and reaped) when its guard is dropped, also when a test
//! fails or panics. The binary is `etcd` from `PATH` (Debian's `etcd-server`, which `make
//! test` installs), or the one `EBMPC_ETCD` names.

use crate::{Guarded, free_port};
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// A running etcd; killed when dropped.
pub struct Etcd {
    pub process: Guarded,
    /// Its client URL, e.g. `http://127.0.0.1:40123`.
    pub endpoint: String,
    pub data_dir: PathBuf,
}

impl Etcd {
    /// Starts etcd with its data under `dir/etcd-data`, and waits until it serves clients.
    pub fn start(dir: &Path) -> Result<Self> {
        let binary = std::env::var_os("EBMPC_ETCD").unwrap_or_else(|| "etcd".into());
        let (client, peer) = (free_port(), free_port());
        let endpoint = format!("http://127.0.0.1:{client}");
        let peer_url = format!("http://127.0.0.1:{peer}");
        let data_dir = dir.join("etcd-data");
        std::fs::create_dir_all(dir)?;
        let mut cmd = Command::new(&binary);
        cmd.arg("--name")
            .arg("test")
            .arg("--data-dir")
            .arg(&data_dir)
            .args(["--listen-client-urls", &endpoint])
            .args(["--advertise-client-urls", &endpoint])
            .args(["--listen-peer-urls", &peer_url])
            .args(["--initial-advertise-peer-urls", &peer_url])
            .args(["--initial-cluster", &format!("test={peer_url}")]);
        let mut process = Guarded::spawn("etcd", cmd, dir.join(format!("etcd-{client}.log")))
            .context("start etcd (install it: apt-get install etcd-server, or `make test`)")?;
        process.wait_for_log("ready to serve client requests", Duration::from_secs(30))?;
        Ok(Self {
            process,
            endpoint,
            data_dir,
        })
    }

    /// The `[fleet]` block of a planner using this etcd (lease of `ttl_seconds`).
    pub fn fleet_toml(&self, ttl_seconds: u64) -> String {
        fleet_toml(&self.endpoint, ttl_seconds)
    }
}

/// The `[fleet]` block of a planner using the etcd at `endpoint`.
pub fn fleet_toml(endpoint: &str, ttl_seconds: u64) -> String {
    format!("[fleet]\netcd = [\"{endpoint}\"]\nlease_ttl_seconds = {ttl_seconds}\n")
}
