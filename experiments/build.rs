//! Embeds MuJoCo's library folder as an rpath in this package's binaries and test binaries, as
//! sim-bridge's build script does for its own: a dependency's `rustc-link-arg` does not reach
//! the packages that use it, and the figures link sim-bridge (and so `libmujoco`) in-process.

use std::env;
use std::path::PathBuf;

const VAR: &str = "MUJOCO_DYNAMIC_LINK_DIR";

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed={VAR}");
    // sim-bridge's build script has already refused a missing or wrong folder, with the fix.
    let Some(dir) = env::var_os(VAR).filter(|d| !d.is_empty()) else {
        return;
    };
    if let Ok(dir) = PathBuf::from(dir).canonicalize() {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{}", dir.display());
    }
}
