//! The field network of `deploy/`: every file in `deploy/zenoh/` loads, and the router of
//! `router.json5`, with certificates from `deploy/certs.sh`, admits only clients with a
//! certificate of the swarm's CA (QUIC with mutual TLS) and lets each principal do only what its
//! role needs. Real zenoh sessions over real QUIC on loopback, opened from the shipped files with only
//! the certificate paths and the address changed.

use std::path::{Path, PathBuf};
use std::time::Duration;
use tacos_shared::keys::Keys;
use tacos_shared::{DroneId, SwarmId};
use tacos_tests::deploy::{make_certs, repo};
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("tacos-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn set(config: &mut zenoh::Config, key: &str, value: &str) -> anyhow::Result<()> {
    config
        .insert_json5(key, value)
        .map_err(|e| anyhow::anyhow!("{key} = {value}: {e}"))
}

fn path_json(p: &Path) -> String {
    format!("{:?}", p.display().to_string())
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::UdpSocket::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// Points `transport/link/tls/<field>` at `certs/<file>` for each pair.
fn set_tls_files(
    c: &mut zenoh::Config,
    certs: &Path,
    files: &[(&str, &str)],
) -> anyhow::Result<()> {
    for (field, file) in files {
        set(
            c,
            &format!("transport/link/tls/{field}"),
            &path_json(&certs.join(file)),
        )?;
    }
    Ok(())
}

fn router_config(certs: &Path, port: u16) -> anyhow::Result<zenoh::Config> {
    let mut c = tacos_bus::router::load(&repo().join("deploy/zenoh/router.json5"))?;
    set(
        &mut c,
        "listen/endpoints",
        &format!("[\"quic/127.0.0.1:{port}\"]"),
    )?;
    set_tls_files(
        &mut c,
        certs,
        &[
            ("root_ca_certificate", "ca.pem"),
            ("listen_certificate", "router.pem"),
            ("listen_private_key", "router-key.pem"),
        ],
    )?;
    Ok(c)
}

/// `deploy/zenoh/client.json5` for `principal`, whose certificate is in `certs` (a client
/// without one when `principal` is `None`). Opening fails after `give_up_ms` instead of
/// retrying for ever, as the file does.
fn client_config(
    certs: &Path,
    principal: Option<&str>,
    port: u16,
    give_up_ms: u32,
) -> anyhow::Result<zenoh::Config> {
    let mut c = zenoh::Config::from_file(repo().join("deploy/zenoh/client.json5"))
        .map_err(|e| anyhow::anyhow!("deploy/zenoh/client.json5: {e}"))?;
    set(
        &mut c,
        "connect/endpoints",
        &format!("[\"quic/127.0.0.1:{port}\"]"),
    )?;
    set_tls_files(&mut c, certs, &[("root_ca_certificate", "ca.pem")])?;
    match principal {
        Some(name) => set_tls_files(
            &mut c,
            certs,
            &[
                ("connect_certificate", &format!("{name}.pem")),
                ("connect_private_key", &format!("{name}-key.pem")),
            ],
        )?,
        None => {
            let tls = "transport/link/tls";
            set(&mut c, &format!("{tls}/enable_mtls"), "false")?;
            set(&mut c, &format!("{tls}/connect_certificate"), "null")?;
            set(&mut c, &format!("{tls}/connect_private_key"), "null")?;
        }
    }
    set(&mut c, "connect/timeout_ms", &give_up_ms.to_string())?;
    set(&mut c, "connect/exit_on_failure", "true")?;
    Ok(c)
}

async fn open(config: zenoh::Config, who: &str) -> anyhow::Result<Session> {
    zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("{who}: {e}"))
}

/// How long an intruder's connection is tried, and a member's.
const INTRUDER_MS: u32 = 3000;
const MEMBER_MS: u32 = 15000;

type Sub = Subscriber<FifoChannelHandler<Sample>>;

async fn subscribe(session: &Session, key: &str) -> anyhow::Result<Sub> {
    session
        .declare_subscriber(key.to_owned())
        .await
        .map_err(|e| anyhow::anyhow!("subscribe {key}: {e}"))
}

async fn put(session: &Session, key: &str, payload: &str) -> anyhow::Result<()> {
    session
        .put(key, payload.to_owned())
        .await
        .map_err(|e| anyhow::anyhow!("put {key}: {e}"))
}

async fn next_payload(sub: &Sub, wait: Duration) -> Option<String> {
    match tokio::time::timeout(wait, sub.recv_async()).await {
        Ok(Ok(sample)) => Some(sample.payload().try_to_string().ok()?.into_owned()),
        _ => None,
    }
}

/// Puts `payload` from `from` until `sub` hears it: the route through the router is up (the
/// subscription has reached it and the publisher).
async fn reaches(from: &Session, key: &str, payload: &str, sub: &Sub) -> anyhow::Result<()> {
    for _ in 0..40 {
        put(from, key, payload).await?;
        if let Some(p) = next_payload(sub, Duration::from_millis(250)).await {
            anyhow::ensure!(p == payload, "{key}: heard {p:?}, expected {payload:?}");
            // Drain the repeats of the probe.
            while next_payload(sub, Duration::from_millis(300))
                .await
                .is_some()
            {}
            return Ok(());
        }
    }
    anyhow::bail!("{payload:?} on {key} never reached its subscriber through the router")
}

/// `intruder` puts on `key`, then `owner` (allowed to) does: the subscriber must hear the
/// owner's sample first, and nothing of the intruder's.
async fn refused(
    intruder: &Session,
    owner: &Session,
    key: &str,
    sub: &Sub,
    what: &str,
) -> anyhow::Result<()> {
    put(intruder, key, "forged").await?;
    // The forged sample, were it routed, would arrive within milliseconds on loopback.
    tokio::time::sleep(Duration::from_millis(500)).await;
    put(owner, key, "genuine").await?;
    let heard = next_payload(sub, Duration::from_secs(5)).await;
    anyhow::ensure!(
        heard.as_deref() == Some("genuine"),
        "{what}: the subscriber heard {heard:?} first, not the owner's sample"
    );
    anyhow::ensure!(
        next_payload(sub, Duration::from_millis(500))
            .await
            .is_none(),
        "{what}: a forged sample came through after the genuine one"
    );
    Ok(())
}

#[test]
fn every_deploy_zenoh_file_loads() -> anyhow::Result<()> {
    let dir = repo().join("deploy/zenoh");
    let mut loaded = 0;
    for entry in std::fs::read_dir(&dir)? {
        let path = entry?.path();
        if path.extension().and_then(|e| e.to_str()) == Some("json5") {
            zenoh::Config::from_file(&path)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            loaded += 1;
        }
    }
    assert!(loaded >= 2, "router.json5 and client.json5 at least");
    // The router's file is one for a router; a client's is refused as one.
    tacos_bus::router::load(&dir.join("router.json5"))?;
    assert!(tacos_bus::router::load(&dir.join("client.json5")).is_err());
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_router_admits_the_swarms_certificates_only_and_each_to_its_own_keys()
-> anyhow::Result<()> {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .try_init();
    let certs = scratch("certs");
    let other_ca = scratch("other-ca");
    make_certs(
        &certs,
        &["router=127.0.0.1", "ground", "world", "alfa", "bravo"],
    )?;
    make_certs(&other_ca, &["alfa"])?;
    let port = free_port()?;
    let _router = tacos_bus::router::open(router_config(&certs, port)?).await?;

    // Without a certificate of the swarm's CA, or without any, nobody gets in; plain UDP (zenoh
    // without QUIC and TLS) on the router's port neither.
    let forged = client_config(&other_ca, Some("alfa"), port, INTRUDER_MS)?;
    let forged = open(forged, "alfa signed by another CA").await;
    assert!(forged.is_err(), "a certificate of another CA was admitted");
    let anonymous = client_config(&certs, None, port, INTRUDER_MS)?;
    assert!(
        open(anonymous, "no certificate").await.is_err(),
        "a client without a certificate was admitted"
    );
    let mut plain = zenoh::Config::default();
    set(&mut plain, "mode", "\"client\"")?;
    set(
        &mut plain,
        "connect/endpoints",
        &format!("[\"udp/127.0.0.1:{port}\"]"),
    )?;
    set(&mut plain, "connect/timeout_ms", "3000")?;
    set(&mut plain, "connect/exit_on_failure", "true")?;
    assert!(
        open(plain, "plain UDP").await.is_err(),
        "a plain UDP client was admitted on the QUIC port"
    );

    let member = async |name: &str| -> anyhow::Result<Session> {
        open(client_config(&certs, Some(name), port, MEMBER_MS)?, name).await
    };
    let ground = member("ground").await?;
    let world = member("world").await?;
    let alfa = member("alfa").await?;
    let bravo = member("bravo").await?;
    let keys = Keys::new(&SwarmId::new("default")?);
    let (a, b) = (DroneId::new("alfa")?, DroneId::new("bravo")?);

    // What each role needs gets through.
    let alfa_actions = subscribe(&alfa, &keys.action(&a)).await?;
    reaches(&ground, &keys.action(&a), "goto", &alfa_actions).await?;
    let bravo_actions = subscribe(&bravo, &keys.action(&b)).await?;
    reaches(&ground, &keys.action(&b), "land", &bravo_actions).await?;
    let heartbeat = subscribe(&bravo, &keys.ground_heartbeat()).await?;
    reaches(&ground, &keys.ground_heartbeat(), "beat", &heartbeat).await?;
    let targets = subscribe(&bravo, &keys.targets()).await?;
    reaches(&world, &keys.targets(), "dog", &targets).await?;
    let statuses = subscribe(&ground, &keys.all_status()).await?;
    reaches(&alfa, &keys.status(&a), "alfa ok", &statuses).await?;
    reaches(&bravo, &keys.status(&b), "bravo ok", &statuses).await?;
    let paths = subscribe(&bravo, &keys.all_paths()).await?;
    reaches(&alfa, &keys.path(&a), "alfa path", &paths).await?;

    // A drone's certificate cannot speak for another drone, the ground or the world; nor can
    // the world's command a drone. (intruder, the one allowed, key, who hears it, what.)
    let (bravo_action, heartbeat_key, targets_key) =
        (keys.action(&b), keys.ground_heartbeat(), keys.targets());
    let (bravo_status, bravo_path, alfa_action) = (keys.status(&b), keys.path(&b), keys.action(&a));
    let forgeries = [
        (
            &alfa,
            &ground,
            &bravo_action,
            &bravo_actions,
            "alfa commanding bravo",
        ),
        (
            &alfa,
            &ground,
            &heartbeat_key,
            &heartbeat,
            "alfa as the ground's heartbeat",
        ),
        (
            &alfa,
            &world,
            &targets_key,
            &targets,
            "alfa placing targets",
        ),
        (
            &alfa,
            &bravo,
            &bravo_status,
            &statuses,
            "alfa as bravo's status",
        ),
        (&alfa, &bravo, &bravo_path, &paths, "alfa as bravo's path"),
        (
            &world,
            &ground,
            &alfa_action,
            &alfa_actions,
            "the world commanding alfa",
        ),
    ];
    for (intruder, owner, key, sub, what) in forgeries {
        refused(intruder, owner, key, sub, what).await?;
    }

    // Liveliness: a drone's own token is seen by the ground; one in another's name is not.
    let alive = ground
        .liveliness()
        .declare_subscriber(keys.all_alive())
        // Tokens declared before this subscription reached the router count too: the two
        // sessions' declarations race to it.
        .history(true)
        .await
        .map_err(|e| anyhow::anyhow!("liveliness subscriber: {e}"))?;
    let _forged_token = alfa
        .liveliness()
        .declare_token(keys.alive(&b))
        .await
        .map_err(|e| anyhow::anyhow!("token: {e}"))?;
    let _token = alfa
        .liveliness()
        .declare_token(keys.alive(&a))
        .await
        .map_err(|e| anyhow::anyhow!("token: {e}"))?;
    let seen = tokio::time::timeout(Duration::from_secs(5), alive.recv_async()).await;
    let seen = match seen {
        Ok(Ok(sample)) => sample.key_expr().as_str().to_owned(),
        other => anyhow::bail!("the ground never saw alfa's liveliness token: {other:?}"),
    };
    assert_eq!(seen, keys.alive(&a), "the first token seen");
    let more = tokio::time::timeout(Duration::from_secs(1), alive.recv_async()).await;
    assert!(
        more.is_err(),
        "a token in bravo's name from alfa's certificate was seen: {more:?}"
    );

    for s in [ground, world, alfa, bravo] {
        let _ = s.close().await;
    }
    let _ = std::fs::remove_dir_all(&certs);
    let _ = std::fs::remove_dir_all(&other_ca);
    Ok(())
}
