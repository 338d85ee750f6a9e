//! What every fleet test starts from: a scratch folder holding the data directory the planners
//! share, an etcd for their leases and fencing tokens, and a Zenoh router (multicast scouting
//! off) that every planner and client connects to.

use crate::client::runtime;
use crate::etcd::Etcd;
use crate::{Guarded, TempDir, free_endpoint, router, serve_data};
use std::path::PathBuf;

/// The shared parts of a fleet under test. The planners a test starts are its own locals,
/// declared after this, so they stop before etcd, the router and the folder go.
pub struct Fleet {
    // Dropped in this order: the router's session, the runtime, etcd, then the folder.
    _router: zenoh::Session,
    pub rt: tokio::runtime::Runtime,
    pub etcd: Etcd,
    /// The router's endpoint.
    pub endpoint: String,
    /// The data directory every planner serves (`dir/shared-data`).
    pub data: PathBuf,
    pub dir: TempDir,
}

impl Fleet {
    /// Starts etcd and the router in a fresh scratch folder named after `name`.
    pub fn start(name: &str) -> Self {
        let dir = TempDir::new(name);
        let data = dir.path().join("shared-data");
        let etcd = Etcd::start(dir.path()).expect("etcd starts");
        let endpoint = free_endpoint();
        let rt = runtime();
        let router = rt.block_on(router(&endpoint)).expect("router starts");
        Self {
            _router: router,
            rt,
            etcd,
            endpoint,
            data,
            dir,
        }
    }

    /// Starts planner `id` with the TOML `config`, serving the shared data directory (its own
    /// files under `dir/{id}`).
    pub fn planner(&self, id: &str, config: &str) -> Guarded {
        serve_data(&self.dir.path().join(id), &self.data, config, None).expect("planner serves")
    }
}
