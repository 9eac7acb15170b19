//! MQTT events against a real broker (Debian's `mosquitto` on a loopback port) and a real
//! subscriber: every state of an inspection in order, its result, a station's retained status, and
//! nothing lost while the broker is away.

use super::*;
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};

/// A mosquitto broker of the test's own, persisting its sessions under `dir` so that a restart on
/// the same port keeps a subscriber's queued messages.
struct Broker {
    dir: std::path::PathBuf,
    port: u16,
    child: Option<std::process::Child>,
    /// The listener's authority, certificate and key (TLS), None: plain TCP.
    tls: Option<(std::path::PathBuf, std::path::PathBuf, std::path::PathBuf)>,
}

impl Broker {
    fn start(dir: &Path) -> Broker {
        Self::start_with(dir, None)
    }

    fn start_with(dir: &Path, tls: Option<(std::path::PathBuf, std::path::PathBuf, std::path::PathBuf)>) -> Broker {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let mut broker = Broker { dir: dir.to_path_buf(), port, child: None, tls };
        broker.restart();
        broker
    }

    fn restart(&mut self) {
        let config = self.dir.join("mosquitto.conf");
        let tls = match &self.tls {
            Some((ca, cert, key)) => {
                format!("cafile {}\ncertfile {}\nkeyfile {}\n", ca.display(), cert.display(), key.display())
            }
            None => String::new(),
        };
        std::fs::write(
            &config,
            format!(
                "listener {} 127.0.0.1\n{tls}allow_anonymous true\npersistence true\npersistence_location {}/\nuser root\n",
                self.port,
                self.dir.display()
            ),
        )
        .unwrap();
        let program = if Path::new("/usr/sbin/mosquitto").exists() { "/usr/sbin/mosquitto" } else { "mosquitto" };
        let child = std::process::Command::new(program)
            .arg("-c")
            .arg(&config)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("mosquitto could not start ({e}): apt-get install mosquitto"));
        self.child = Some(child);
        for _ in 0..100 {
            if std::net::TcpStream::connect(("127.0.0.1", self.port)).is_ok() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        panic!("mosquitto did not listen on {}", self.port);
    }

    /// Stops it as an operator would (SIGTERM: it saves its sessions).
    fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            // SAFETY: kill sends a signal to the broker's own process id.
            unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
            child.wait().unwrap();
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// A subscriber to `filter` that stays subscribed across broker restarts (a persistent session);
/// every message as (topic, retained, payload).
async fn subscriber(
    port: u16,
    id: &str,
    filter: &str,
    persistent: bool,
) -> tokio::sync::mpsc::UnboundedReceiver<(String, bool, Value)> {
    subscriber_over(port, id, filter, persistent, None).await
}

async fn subscriber_over(
    port: u16,
    id: &str,
    filter: &str,
    persistent: bool,
    tls_roots: Option<Vec<u8>>,
) -> tokio::sync::mpsc::UnboundedReceiver<(String, bool, Value)> {
    let mut options = MqttOptions::new(id, "127.0.0.1", port);
    if let Some(ca) = tls_roots {
        options.set_transport(rumqttc::Transport::tls(ca, None, None));
    }
    options.set_clean_session(!persistent);
    options.set_keep_alive(Duration::from_secs(5));
    let (client, mut events) = AsyncClient::new(options, 100);
    client.subscribe(filter, QoS::AtLeastOnce).await.unwrap();
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    let (subscribed_tx, subscribed) = tokio::sync::oneshot::channel();
    let mut subscribed_tx = Some(subscribed_tx);
    tokio::spawn(async move {
        let _client = client;
        loop {
            match events.poll().await {
                Ok(Event::Incoming(Packet::SubAck(_))) => {
                    if let Some(s) = subscribed_tx.take() {
                        let _ = s.send(());
                    }
                }
                Ok(Event::Incoming(Packet::Publish(p))) => {
                    let payload: Value = serde_json::from_slice(&p.payload).expect("JSON payloads");
                    if tx.send((p.topic.clone(), p.retain, payload)).is_err() {
                        return;
                    }
                }
                Ok(_) => {}
                // The broker away: try again, as a subscriber in a plant would.
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        }
    });
    tokio::time::timeout(Duration::from_secs(10), subscribed).await.expect("subscribed").unwrap();
    rx
}

/// Messages about inspection `id` until its result arrives: its states (duplicates, which
/// at-least-once allows, must repeat their event id and payload) and the result.
async fn until_result(
    rx: &mut tokio::sync::mpsc::UnboundedReceiver<(String, bool, Value)>,
    site: &str,
    id: &str,
) -> (Vec<(i64, String)>, Value) {
    let mut states: Vec<(i64, String)> = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    loop {
        let (topic, _, payload) = tokio::time::timeout_at(deadline, rx.recv())
            .await
            .unwrap_or_else(|_| panic!("no result for {id}; states so far {states:?}"))
            .unwrap();
        if topic == format!("crestscan/{site}/inspections/{id}/state") {
            let event = (payload["event_id"].as_i64().unwrap(), payload["status"].as_str().unwrap().to_string());
            match states.iter().find(|s| s.0 == event.0) {
                Some(seen) => assert_eq!(seen, &event, "a repeated message is the same event"),
                None => states.push(event),
            }
        } else if topic == format!("crestscan/{site}/inspections/{id}/result") {
            return (states, payload);
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_state_reaches_a_subscriber_in_order_and_none_is_lost_while_the_broker_is_away() {
    let dir = tempfile::tempdir().unwrap();
    let mut broker = Broker::start(dir.path());
    let port = broker.port;
    let mut rx = subscriber(port, "it-line-monitor", "crestscan/plant-a/#", true).await;
    let app = spawn_app_with(|s| {
        s.mqtt_url = Some(format!("mqtt://127.0.0.1:{port}"));
        s.mqtt_site = "plant-a".into();
    })
    .await;

    let created = app.client.post(app.url("/v1/stations")).json(&serde_json::json!({"name": "line-3"})).send().await;
    assert_eq!(created.unwrap().status(), StatusCode::CREATED);
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    let row = app.wait(&id, Duration::from_secs(120)).await;
    assert_eq!(row["status"], "succeeded");
    let (states, result) = until_result(&mut rx, "plant-a", &id).await;
    let names: Vec<&str> = states.iter().map(|s| s.1.as_str()).collect();
    assert_eq!(names, ["queued", "running", "succeeded"], "every state, in order");
    assert!(states.windows(2).all(|w| w[0].0 < w[1].0), "event ids rise: {states:?}");
    assert_eq!(result["verdict"], row["verdict"]);
    assert_eq!(result["decision"], row["decision"]);
    assert_eq!(result["review_required"], row["review_required"]);
    assert_eq!(result["report"], format!("/v1/inspections/{id}/report"));

    // A late subscriber reads the station's status at once: it is retained.
    let mut late = subscriber(port, "it-late", "crestscan/plant-a/stations/#", false).await;
    let (topic, retained, status) =
        tokio::time::timeout(Duration::from_secs(10), late.recv()).await.expect("the retained status").unwrap();
    assert_eq!(topic, "crestscan/plant-a/stations/line-3/status");
    assert!(retained);
    assert_eq!(status["status"], "unqualified");

    // The broker goes away: the inspection runs all the same, and its events wait for it.
    broker.stop();
    let second = app.submit(ci_tar(), "?client_reference=while-away").await;
    assert_eq!(second.status(), StatusCode::ACCEPTED);
    let second = second.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&second, Duration::from_secs(120)).await["status"], "succeeded");
    assert!(rx.try_recv().is_err(), "nothing arrives while the broker is down");
    broker.restart();
    let (states, result) = until_result(&mut rx, "plant-a", &second).await;
    let names: Vec<&str> = states.iter().map(|s| s.1.as_str()).collect();
    assert_eq!(names, ["queued", "running", "succeeded"], "none lost: {states:?}");
    assert_eq!(result["inspection_id"], second);
    app.stop().await;
}

/// `mqtts://` with `mqtt_ca_file`: the publisher checks the broker's certificate against that
/// authority and delivers over TLS.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_reach_a_tls_broker_checked_against_its_authority() {
    let dir = tempfile::tempdir().unwrap();
    let (ca, cert, key) = crate::common::self_signed(dir.path(), "broker");
    let broker = Broker::start_with(dir.path(), Some((ca.clone(), cert, key)));
    let port = broker.port;
    let roots = std::fs::read(&ca).unwrap();
    let mut rx = subscriber_over(port, "it-tls-monitor", "crestscan/plant-tls/#", false, Some(roots)).await;
    let app = spawn_app_with(|s| {
        s.mqtt_url = Some(format!("mqtts://127.0.0.1:{port}"));
        s.mqtt_site = "plant-tls".into();
        s.mqtt_ca_file = Some(ca.clone());
    })
    .await;
    let id = app.submit(ci_tar(), "").await.json::<Value>().await.unwrap()["id"].as_str().unwrap().to_string();
    assert_eq!(app.wait(&id, Duration::from_secs(120)).await["status"], "succeeded");
    let (states, result) = until_result(&mut rx, "plant-tls", &id).await;
    assert_eq!(states.iter().map(|s| s.1.as_str()).collect::<Vec<_>>(), ["queued", "running", "succeeded"]);
    assert_eq!(result["inspection_id"], id);
    app.stop().await;
    drop(broker);
}

/// `mqtts://` without `mqtt_ca_file`: the broker's certificate is checked against the system's
/// roots, here the test's authority given as the real binary's `SSL_CERT_FILE` (the variable the
/// system-root loader honours, set for that process alone).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_ca_file_the_system_roots_check_the_broker() {
    let dir = tempfile::tempdir().unwrap();
    let (ca, cert, key) = crate::common::self_signed(dir.path(), "broker");
    let broker = Broker::start_with(dir.path(), Some((ca.clone(), cert, key)));
    let port = broker.port;
    let mut rx =
        subscriber_over(port, "it-system-roots", "crestscan/plant-sys/#", false, Some(std::fs::read(&ca).unwrap()))
            .await;
    let data = tempfile::tempdir().unwrap();
    let url = format!("mqtts://127.0.0.1:{port}");
    let (child, base) = start_binary_env(
        data.path(),
        &["--mqtt-url", &url, "--mqtt-site", "plant-sys"],
        &[("SSL_CERT_FILE", ca.as_path())],
    );
    let client = client();
    let id = submit_ci_to(&client, &base).await;
    let (states, result) = until_result(&mut rx, "plant-sys", &id).await;
    assert_eq!(states.iter().map(|s| s.1.as_str()).collect::<Vec<_>>(), ["queued", "running", "succeeded"]);
    assert_eq!(result["inspection_id"], id);
    drop(child); // killed by its guard, as on a failed assertion
    drop(broker);
}
