//! Makes sim-bridge's binaries and test binaries find `libmujoco` without `LD_LIBRARY_PATH`.
//!
//! mujoco-rs links `libmujoco` dynamically from `MUJOCO_DYNAMIC_LINK_DIR` (set by
//! `.cargo/config.toml` to the folder `deploy/install-mujoco.sh` fills) but adds no run-time
//! search path, so a plain `cargo run` would fail to load the library. We embed that folder as an
//! rpath. `rustc-link-arg` covers every linked target of this package: the binary, the unit-test
//! and integration-test binaries, examples and benches.

use std::env;
use std::path::{Path, PathBuf};

const VAR: &str = "MUJOCO_DYNAMIC_LINK_DIR";
const INSTALL_HINT: &str = "run deploy/install-mujoco.sh (it installs MuJoCo 3.17.0 into .mujoco/lib, \
     which .cargo/config.toml points MUJOCO_DYNAMIC_LINK_DIR at), or set MUJOCO_DYNAMIC_LINK_DIR \
     to the absolute path of the `lib` folder of your own MuJoCo 3.17.0";

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed={VAR}");

    let dir = match env::var_os(VAR) {
        Some(dir) if !dir.is_empty() => PathBuf::from(dir),
        _ => fail(&format!("{VAR} is not set")),
    };
    let dir = match dir.canonicalize() {
        Ok(dir) => dir,
        Err(e) => fail(&format!("{VAR}={} cannot be resolved: {e}", dir.display())),
    };
    if !has_mujoco_library(&dir) {
        fail(&format!(
            "{VAR}={} holds no libmujoco shared library",
            dir.display()
        ));
    }
    // The library folder (cargo watches the files in it): a reinstall must relink.
    println!("cargo:rerun-if-changed={}", dir.display());
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", dir.display());
}

/// Whether `dir` holds `libmujoco.so` (Linux) or `libmujoco.dylib` (macOS), the names the
/// linker's `-lmujoco` looks for.
fn has_mujoco_library(dir: &Path) -> bool {
    ["libmujoco.so", "libmujoco.dylib"]
        .iter()
        .any(|name| dir.join(name).exists())
}

fn fail(problem: &str) -> ! {
    eprintln!("error: {problem}.\n  To fix: {INSTALL_HINT}.");
    panic!("sim-bridge needs MuJoCo 3.17.0: {problem}; {INSTALL_HINT}");
}
