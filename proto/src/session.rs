//! How every ebmpc process joins Zenoh: explicit endpoints, no multicast scouting.
//!
//! Since zenoh 1.9 peers do not relay for each other, so processes are connected explicitly:
//! each one `listen`s and/or `connect`s to endpoints (or to a `zenohd` router). Multicast
//! scouting is off so that a test or a lab machine never joins a stranger's session by accident.

/// Where a process listens and what it connects to.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Endpoints {
    /// Endpoints to listen on, e.g. `tcp/127.0.0.1:7447`.
    pub listen: Vec<String>,
    /// Endpoints to connect to (peers or a router).
    pub connect: Vec<String>,
}

/// A Zenoh configuration that could not be built.
#[derive(Debug, thiserror::Error)]
#[error("invalid zenoh configuration ({what}): {reason}")]
pub struct SessionConfigError {
    what: String,
    reason: String,
}

/// The Zenoh configuration for `endpoints`, starting from `base` (a user's config file) or the
/// default peer configuration.
pub fn zenoh_config(
    endpoints: &Endpoints,
    base: Option<zenoh::Config>,
) -> Result<zenoh::Config, SessionConfigError> {
    let mut config = base.unwrap_or_default();
    let mut set = |key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| SessionConfigError {
                what: format!("{key} = {value}"),
                reason: e.to_string(),
            })
    };
    set("scouting/multicast/enabled", "false".into())?;
    if !endpoints.listen.is_empty() {
        set("listen/endpoints", json_list(&endpoints.listen))?;
    }
    if !endpoints.connect.is_empty() {
        set("connect/endpoints", json_list(&endpoints.connect))?;
    }
    Ok(config)
}

fn json_list(items: &[String]) -> String {
    serde_json::to_string(items).expect("strings serialise")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builds_a_config_with_explicit_endpoints() {
        let endpoints = Endpoints {
            listen: vec!["tcp/127.0.0.1:0".into()],
            connect: vec!["tcp/127.0.0.1:7447".into()],
        };
        let config = zenoh_config(&endpoints, None).unwrap();
        let text = format!("{config}");
        assert!(text.contains("127.0.0.1:7447"), "{text}");
    }

    #[test]
    fn rejects_bad_endpoints() {
        let endpoints = Endpoints {
            listen: vec!["not an endpoint".into()],
            connect: vec![],
        };
        assert!(zenoh_config(&endpoints, None).is_err());
    }
}
