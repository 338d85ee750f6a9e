//! The multi-host deployment of docs/deploy.md, on loopback: certificates from
//! `deploy/make-certs.sh`, a router running `deploy/zenohd.json5`, and a planner and an agent
//! (the Python example) that are its clients over mutual TLS with `deploy/zenoh-client.json5`.
//! Only the site-specific strings of those files (certificate paths, endpoints) are replaced.
//!
//! Checked: the configs load; planner and agent learn through the router; `planner-service
//! status` reaches the planner through it; the access control forwards `ebmpc/**` and nothing
//! else; a client without a certificate is turned away; `deploy/planner.toml` is a valid config.

use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::python::run_controller;
use ebmpc_e2e::{TempDir, free_port, serve, status_cli, workspace};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// `text` with every `(from, to)` replaced; each `from` must occur, so that a change to the
/// deploy files cannot silently leave this test checking something else.
fn substitute(text: &str, replacements: &[(&str, String)]) -> String {
    let mut text = text.to_string();
    for (from, to) in replacements {
        assert!(text.contains(from), "`{from}` not found in the deploy file");
        text = text.replace(from, to);
    }
    text
}

fn read_deploy(name: &str) -> String {
    std::fs::read_to_string(workspace().join("deploy").join(name)).unwrap()
}

/// deploy/zenoh-client.json5 for the client `name`, connecting to the router's TLS endpoint.
fn client_config(certs: &Path, name: &str, tls_port: u16) -> String {
    substitute(
        &read_deploy("zenoh-client.json5"),
        &[
            (
                "tls/router.example.org:7448",
                format!("tls/localhost:{tls_port}"),
            ),
            ("/etc/ebmpc/tls/ca.pem", path(certs, "ca.pem")),
            (
                "/etc/ebmpc/tls/client.pem",
                path(certs, &format!("{name}.pem")),
            ),
            (
                "/etc/ebmpc/tls/client-key.pem",
                path(certs, &format!("{name}-key.pem")),
            ),
        ],
    )
}

fn path(dir: &Path, file: &str) -> String {
    dir.join(file).to_str().unwrap().to_string()
}

/// A client session of the router over its loopback TCP endpoint.
async fn tcp_client(tcp_port: u16) -> zenoh::Session {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"client\"".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
        (
            "connect/endpoints",
            format!("[\"tcp/127.0.0.1:{tcp_port}\"]"),
        ),
    ] {
        config.insert_json5(key, &value).unwrap();
    }
    zenoh::open(config).await.unwrap()
}

#[test]
fn planner_and_agent_learn_through_a_tls_router_with_access_control() {
    let dir = TempDir::new("deploy");
    let certs = dir.path().join("tls");
    let made = Command::new("bash")
        .arg(workspace().join("deploy/make-certs.sh"))
        .arg(&certs)
        .args(["localhost", "planner-1", "agent-1"])
        .output()
        .unwrap();
    assert!(
        made.status.success(),
        "make-certs.sh: {}",
        String::from_utf8_lossy(&made.stderr)
    );

    // The router, in this process: deploy/zenohd.json5 with this test's ports and certificates.
    let (tcp_port, tls_port) = (free_port(), free_port());
    let router_text = substitute(
        &read_deploy("zenohd.json5"),
        &[
            ("tcp/127.0.0.1:7447", format!("tcp/127.0.0.1:{tcp_port}")),
            ("tls/0.0.0.0:7448", format!("tls/127.0.0.1:{tls_port}")),
            ("/etc/ebmpc/tls/ca.pem", path(&certs, "ca.pem")),
            ("/etc/ebmpc/tls/router.pem", path(&certs, "router.pem")),
            (
                "/etc/ebmpc/tls/router-key.pem",
                path(&certs, "router-key.pem"),
            ),
        ],
    );
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let router_config = zenoh::Config::from_json5(&router_text).expect("zenohd.json5 loads");
    let router = runtime
        .block_on(async { zenoh::open(router_config).await })
        .expect("the router starts");

    // The planner: a TLS client of the router, listening on nothing (planner.toml layout (b)).
    let planner_zenoh = dir.path().join("planner-zenoh.json5");
    std::fs::write(&planner_zenoh, client_config(&certs, "planner-1", tls_port)).unwrap();
    let config = PlannerConfig::new("site-planner", Sizes::SMALL)
        .line(format!("zenoh_config = \"{}\"", planner_zenoh.display()))
        .toml();
    let mut planner = serve(dir.path(), &config, None).expect("planner serves");

    // The agent: the Python example, a TLS client of the router with its own certificate.
    let agent_zenoh = dir.path().join("agent-zenoh.json5");
    std::fs::write(&agent_zenoh, client_config(&certs, "agent-1", tls_port)).unwrap();
    let args = [
        "--zenoh-config",
        agent_zenoh.to_str().unwrap(),
        "--run",
        "site-run",
        "--agent",
        "agent-1",
        "--episodes",
        "2",
        "--steps",
        "15",
        "--override",
        "exploration_episodes=1",
    ];
    let (status, agent_log) = run_controller(dir.path(), &args, Duration::from_secs(300)).unwrap();
    assert!(
        status.success(),
        "agent through the router failed: {status}\n{agent_log}\nplanner:\n{}",
        planner.log()
    );
    assert!(
        agent_log.contains("stored: run `site-run` holds 2 episodes, 30 transitions"),
        "{agent_log}"
    );

    // `status` through the router (its loopback TCP endpoint) finds the planner and its run.
    let (ok, table, err) = status_cli(&format!("tcp/127.0.0.1:{tcp_port}"), &[]).unwrap();
    assert!(ok.success(), "{err}");
    assert!(table.starts_with("planner site-planner "), "{table}");
    assert!(
        table
            .lines()
            .any(|l| l.starts_with("site-run ") && l.contains(" 30 ")),
        "{table}"
    );

    runtime.block_on(async {
        // Access control: `ebmpc/**` is routed between two clients, any other key is not.
        let (a, b) = (tcp_client(tcp_port).await, tcp_client(tcp_port).await);
        let allowed = a.declare_subscriber("ebmpc/acl-check/**").await.unwrap();
        let denied = a.declare_subscriber("other/**").await.unwrap();
        let started = Instant::now();
        let arrived = loop {
            // The denied put goes first on the same path: had it been forwarded, it would be
            // in its channel before the allowed one arrives.
            b.put("other/acl-check", "must not pass").await.unwrap();
            b.put("ebmpc/acl-check/x", "passes").await.unwrap();
            match tokio::time::timeout(Duration::from_millis(200), allowed.recv_async()).await {
                Ok(sample) => break sample.unwrap(),
                Err(_) => assert!(
                    started.elapsed() < Duration::from_secs(30),
                    "nothing routed on ebmpc/**"
                ),
            }
        };
        assert_eq!(arrived.key_expr().as_str(), "ebmpc/acl-check/x");
        assert!(
            denied.try_recv().unwrap().is_none(),
            "the router forwarded a key outside ebmpc/**"
        );
        a.close().await.unwrap();
        b.close().await.unwrap();

        // Mutual TLS: a client without a certificate of the site's CA cannot connect.
        let anonymous = substitute(
            &client_config(&certs, "agent-1", tls_port),
            &[
                ("enable_mtls: true", "enable_mtls: false".to_string()),
                (
                    &format!("connect_certificate: \"{}\",", path(&certs, "agent-1.pem")),
                    String::new(),
                ),
                (
                    &format!(
                        "connect_private_key: \"{}\",",
                        path(&certs, "agent-1-key.pem")
                    ),
                    String::new(),
                ),
            ],
        );
        let refused = zenoh::open(zenoh::Config::from_json5(&anonymous).unwrap()).await;
        assert!(refused.is_err(), "a client without a certificate got in");
    });

    let status = planner.terminate(Duration::from_secs(30)).unwrap();
    assert!(
        status.success(),
        "planner exit: {status}\n{}",
        planner.log()
    );
    runtime.block_on(async { router.close().await }).unwrap();
}

#[test]
fn the_example_planner_config_is_valid() {
    let config =
        planner_service::config::ServiceConfig::load(&workspace().join("deploy/planner.toml"))
            .expect("deploy/planner.toml loads");
    config.validate().expect("and is valid");
    assert_eq!(
        config.prefix, "ebmpc",
        "the router's ACL allows ebmpc/** only"
    );
}
