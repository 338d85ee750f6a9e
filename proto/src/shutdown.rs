//! How every ebmpc process learns that it is asked to stop: SIGINT (Ctrl-C in a terminal) or
//! SIGTERM (systemd, `kill`, a test harness). Both mean the same thing — finish or abandon the
//! message in hand, flush, close the session — so the daemon and the bridge share this one
//! definition instead of each listening for whichever signal its author thought of.

/// Resolves with the signal's name when the process is asked to stop; an error if the signal
/// handlers cannot be installed (the caller decides whether to run on without them).
pub async fn shutdown_signal() -> std::io::Result<&'static str> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let mut term = signal(SignalKind::terminate())?;
        let mut int = signal(SignalKind::interrupt())?;
        tokio::select! {
            _ = term.recv() => Ok("SIGTERM"),
            _ = int.recv() => Ok("SIGINT"),
        }
    }
    #[cfg(not(unix))]
    {
        tokio::signal::ctrl_c().await?;
        Ok("Ctrl-C")
    }
}
