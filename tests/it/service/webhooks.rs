//! Webhooks under faults: the real binary, SIGKILLed at random moments while it runs and
//! delivers, restarted on the same data directory; a receiver on loopback that verifies every
//! signature with its own HMAC; and a destination that must never be contacted.

use super::*;
use axum::body::Bytes;
use axum::http::{HeaderMap, StatusCode as AxumStatus};
use base64::Engine;
use hmac::{Hmac, Mac};
use rand::{Rng, SeedableRng};
use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// One request the receiver took: its webhook-id, whether its signature held, the event.
#[derive(Clone, Debug)]
struct Received {
    path: String,
    id: String,
    signed: bool,
    event: Value,
    answered: u16,
}

#[derive(Default)]
struct Receiver {
    got: Mutex<Vec<Received>>,
}

const SECRET_OLD: &str = "whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw";
const SECRET_NEW: &str = "whsec_c2VjcmV0LW9mLWEtcm90YXRlZC1lbmRwb2ludC0zMmI=";
const SECRET_CALLBACK: &str = "whsec_Y2FsbGJhY2stc2VjcmV0LW9mLXRoZS1tZXMtMDAwMDE=";

/// Verifies a Standard Webhooks signature the way a receiver would, written here from the
/// specification rather than with the server's code: any `v1,` signature made with `secret` over
/// `id.timestamp.body`, and a timestamp within five minutes.
fn verify(secret: &str, headers: &HeaderMap, body: &[u8]) -> bool {
    let header = |name: &str| headers.get(name).and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
    let (id, timestamp, signatures) = (header("webhook-id"), header("webhook-timestamp"), header("webhook-signature"));
    let Ok(ts) = timestamp.parse::<i64>() else { return false };
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs() as i64;
    if (now - ts).abs() > 300 {
        return false;
    }
    let key = base64::engine::general_purpose::STANDARD.decode(secret.strip_prefix("whsec_").unwrap()).unwrap();
    let mut mac = Hmac::<sha2::Sha256>::new_from_slice(&key).unwrap();
    mac.update(format!("{id}.{timestamp}.").as_bytes());
    mac.update(body);
    let expected = format!("v1,{}", base64::engine::general_purpose::STANDARD.encode(mac.finalize().into_bytes()));
    signatures.split(' ').any(|s| s == expected)
}

/// The MES's receiver on loopback: `/hook` (the endpoint, signed with the old and the new secret),
/// `/callback` (the submission's own), `/moved` (answers 307 to the honeypot). The first request
/// of each webhook-id gets 503, so every delivery is retried; later ones 200 after 150 ms, which
/// leaves the kills time to land while a delivery is under way.
async fn start_receiver(honeypot: String) -> (Arc<Receiver>, String) {
    let receiver = Arc::new(Receiver::default());
    let take = |path: &'static str, secret: &'static str, receiver: Arc<Receiver>, honeypot: String| {
        move |headers: HeaderMap, body: Bytes| {
            let receiver = receiver.clone();
            let honeypot = honeypot.clone();
            async move {
                let id = headers.get("webhook-id").and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
                let signed = verify(secret, &headers, &body);
                let event: Value = serde_json::from_slice(&body).unwrap_or(Value::Null);
                let seen = receiver.got.lock().unwrap().iter().any(|r| r.id == id);
                let answer = if path == "/moved" {
                    AxumStatus::TEMPORARY_REDIRECT
                } else if !seen {
                    AxumStatus::SERVICE_UNAVAILABLE
                } else {
                    tokio::time::sleep(Duration::from_millis(150)).await;
                    AxumStatus::OK
                };
                receiver.got.lock().unwrap().push(Received {
                    path: path.into(),
                    id,
                    signed,
                    event,
                    answered: answer.as_u16(),
                });
                let mut headers = HeaderMap::new();
                headers.insert("location", format!("{honeypot}/stolen").parse().unwrap());
                (answer, headers)
            }
        }
    };
    let app = axum::Router::new()
        .route("/hook", axum::routing::post(take("/hook", SECRET_NEW, receiver.clone(), honeypot.clone())))
        .route("/callback", axum::routing::post(take("/callback", SECRET_CALLBACK, receiver.clone(), honeypot.clone())))
        .route("/moved", axum::routing::post(take("/moved", SECRET_OLD, receiver.clone(), honeypot)));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (receiver, base)
}

/// A listener that only counts the connections made to it.
async fn start_honeypot() -> (Arc<AtomicUsize>, String) {
    let hits = Arc::new(AtomicUsize::new(0));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    let counted = hits.clone();
    tokio::spawn(async move {
        while let Ok((_stream, _)) = listener.accept().await {
            counted.fetch_add(1, Ordering::SeqCst);
        }
    });
    (hits, base)
}

/// The service's process (SIGKILLed when dropped, as every [`super::ServeChild`] is).
struct Service(super::ServeChild);

impl Service {
    /// SIGKILL, and the process reaped.
    fn kill(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start(data: &Path, args: &[&str]) -> (Service, String) {
    let (child, base) = start_binary(data, args);
    (Service(child), base)
}

async fn inspection_status(client: &reqwest::Client, base: &str, id: &str) -> Option<String> {
    let response = client.get(format!("{base}/v1/inspections/{id}")).send().await.ok()?;
    let v: Value = response.json().await.ok()?;
    v["status"].as_str().map(str::to_string)
}

/// Every terminal state reaches the endpoint and the callback at least once, each time under the
/// same webhook-id and with a signature that holds, through SIGKILLs at random moments; the
/// disallowed destination is refused at submission and a redirect to it is not followed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn webhooks_survive_kill_9_signed_and_only_to_allowed_destinations() {
    let (honeypot_hits, honeypot) = start_honeypot().await;
    let (receiver, mes) = start_receiver(honeypot.clone()).await;
    let data = tempfile::tempdir().unwrap();
    let config = data.path().join("crestscan.toml");
    std::fs::write(
        &config,
        format!(
            "callback_origins = [\"{mes}\"]\ncallback_secrets = [\"{SECRET_CALLBACK}\"]\n\
             webhook_retry_seconds = 0.2\nwebhook_max_attempts = 4\nwebhook_timeout_seconds = 5\n\
             [[webhooks]]\nname = \"mes\"\nurl = \"{mes}/hook\"\nsecrets = [\"{SECRET_OLD}\", \"{SECRET_NEW}\"]\n\
             [[webhooks]]\nname = \"moved\"\nurl = \"{mes}/moved\"\nsecrets = [\"{SECRET_OLD}\"]\nevents = [\"inspection.canceled\"]\n"
        ),
    )
    .unwrap();
    let config = config.to_str().unwrap().to_string();
    let args = ["--config", &config, "--lease-seconds", "1", "--heartbeat-seconds", "0.2", "--poll-interval-ms", "50"];
    let client = super::client();
    let (mut service, mut base) = start(&data.path().join("service"), &args);

    let submit = |base: &str, callback: &str| {
        client
            .post(format!("{base}/v1/inspections?callback_url={callback}"))
            .header("content-type", "application/x-tar")
            .body(ci_tar())
            .send()
    };
    // A callback to anywhere but the allowed origins is refused, before anything is stored.
    let refused = submit(&base, &format!("{honeypot}/hook")).await.unwrap();
    let problem = problem(refused, StatusCode::UNPROCESSABLE_ENTITY, "callback_not_allowed").await;
    assert_eq!(problem["culprit"], "callback_url", "{problem}");

    let with_callback = submit(&base, &format!("{mes}/callback")).await.unwrap();
    assert_eq!(with_callback.status(), StatusCode::ACCEPTED);
    let run: Value = with_callback.json().await.unwrap();
    // Only the callback's origin is shown (its query could hold the receiver's token).
    assert_eq!(run["callback_origin"], format!("{mes}"), "{run}");
    assert!(!run.to_string().contains("/callback"), "{run}");
    let run = run["id"].as_str().unwrap().to_string();
    let mut ids = vec![run.clone()];
    for _ in 0..2 {
        let id = submit_ci_to(&client, &base).await;
        let canceled = client.post(format!("{base}/v1/inspections/{id}/cancel")).send().await.unwrap();
        assert_eq!(canceled.status(), StatusCode::OK);
        ids.push(id);
    }

    // SIGKILL at random moments (seeded) while the job runs and the deliveries go out.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(29);
    for _ in 0..4 {
        tokio::time::sleep(Duration::from_millis(rng.random_range(100..1500))).await;
        service.kill();
        (service, base) = start(&data.path().join("service"), &args);
    }

    // Then every terminal state arrives: to `mes` for all three, to the callback for the run.
    let expected: Vec<(String, &str)> =
        ids.iter().map(|id| (id.clone(), "/hook")).chain([(run.clone(), "/callback")]).collect();
    let deadline = Instant::now() + Duration::from_secs(300);
    loop {
        let delivered = {
            let got = receiver.got.lock().unwrap();
            expected.iter().all(|(id, path)| {
                got.iter().any(|r| r.path == *path && r.answered == 200 && r.event["data"]["id"] == id.as_str())
            })
        };
        if delivered {
            break;
        }
        assert!(Instant::now() < deadline, "not all delivered: {:?}", receiver.got.lock().unwrap());
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    let got = receiver.got.lock().unwrap().clone();
    assert!(got.iter().all(|r| r.signed), "every request carries a signature that holds: {got:?}");
    let mut ids_per_target: HashMap<(String, String), std::collections::BTreeSet<String>> = HashMap::new();
    for r in &got {
        let inspection = r.event["data"]["id"].as_str().unwrap().to_string();
        ids_per_target.entry((inspection, r.path.clone())).or_default().insert(r.id.clone());
    }
    for ((inspection, path), webhook_ids) in &ids_per_target {
        assert_eq!(webhook_ids.len(), 1, "{inspection} to {path}: one webhook-id over every attempt: {webhook_ids:?}");
    }
    for id in &ids {
        let status = inspection_status(&client, &base, id).await.unwrap();
        let events: Vec<&Received> = got.iter().filter(|r| r.event["data"]["id"] == id.as_str()).collect();
        assert!(
            events
                .iter()
                .all(|r| r.event["type"] == format!("inspection.{status}") && r.event["data"]["status"] == status),
            "{id} is {status}: {events:?}"
        );
    }
    assert_eq!(inspection_status(&client, &base, &ids[1]).await.as_deref(), Some("canceled"));

    // The redirecting endpoint: attempted, its redirect not followed, given up after 4 attempts.
    let deadline = Instant::now() + Duration::from_secs(60);
    let moved = loop {
        let page = get_json(&client, &format!("{base}/v1/webhooks/deliveries?inspection_id={}", ids[1])).await;
        let moved = page["deliveries"].as_array().unwrap().iter().find(|d| d["endpoint"] == "moved").cloned();
        if let Some(m) = moved.filter(|m| m["status"] == "failed") {
            break m;
        }
        assert!(Instant::now() < deadline, "the redirecting endpoint was not given up: {page}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(moved["attempts"], 4, "{moved}");
    assert!(moved["last_error"].as_str().unwrap().contains("not followed"), "{moved}");
    assert_eq!(moved["attempt_log"].as_array().unwrap().len(), 4, "{moved}");
    assert_eq!(moved["attempt_log"][0]["status_code"], 307, "{moved}");
    // The receiver may have answered an attempt whose process was killed before it recorded
    // it: that delivery is attempted again once its lease lapses, under the same id.
    let deadline = Instant::now() + Duration::from_secs(120);
    let page = loop {
        let page =
            get_json(&client, &format!("{base}/v1/webhooks/deliveries?inspection_id={run}&status=delivered")).await;
        if page["deliveries"].as_array().unwrap().len() == 2 {
            break page;
        }
        assert!(Instant::now() < deadline, "the run's deliveries are not recorded as delivered: {page}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let endpoints: std::collections::BTreeSet<&str> =
        page["deliveries"].as_array().unwrap().iter().map(|d| d["endpoint"].as_str().unwrap()).collect();
    assert_eq!(endpoints, ["callback", "mes"].into(), "{page}");
    for d in page["deliveries"].as_array().unwrap() {
        // Every recorded attempt is in the log, the last one the 200. (The receiver answers each
        // id's first request with 503; an attempt cut off by a kill goes unrecorded.)
        let log = d["attempt_log"].as_array().unwrap();
        assert_eq!(d["attempts"], log.len(), "{d}");
        assert_eq!(log.last().unwrap()["status_code"], 200, "{d}");
        assert!(log[..log.len() - 1].iter().all(|a| a["status_code"] != 200 && a["error"].is_string()), "{d}");
    }
    service.kill();
    assert_eq!(honeypot_hits.load(Ordering::SeqCst), 0, "the disallowed destination was contacted");
}
