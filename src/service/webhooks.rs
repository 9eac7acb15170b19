//! Webhooks: every inspection's terminal state is told to the configured endpoints that want the
//! event and to the submission's own `callback_url`, signed per Standard Webhooks
//! (<https://www.standardwebhooks.com>): `webhook-id` (the same on every attempt),
//! `webhook-timestamp`, and `webhook-signature: v1,<base64 HMAC-SHA256 of id.timestamp.body>`, one
//! signature per active secret so that a secret can be rotated without a gap.
//!
//! Delivery runs from an outbox in the database ([`crate::service::store`]): the dispatcher turns
//! each newly terminal inspection into deliveries in one transaction with marking it announced,
//! then attempts due deliveries under a lease. A process killed at any moment leaves them pending
//! (or leased, until the lease lapses): every terminal state is delivered at least once, with the
//! same `webhook-id`. Failures are retried with exponential back-off and jitter up to
//! `webhook_max_attempts`. Destinations are only the configured endpoints and `callback_url`s
//! whose origin is in `callback_origins`; redirects are never followed.

use crate::service::config::Settings;
use crate::service::store::{AttemptOutcome, AttemptRow, DeliveryRow, InspectionRow, NewDelivery, Store, now_ms};
pub use crate::service::webhook_settings::{CALLBACK, EndpointSettings, EventType, Secret, origin_of, signature};
use crate::service::wire::Inspection;
use serde::Serialize;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::watch;

/// Whether the settings let a submission's `callback_url` be `url`; the reason when not.
pub fn callback_allowed(settings: &Settings, url: &str) -> Result<(), String> {
    if url.len() > 2048 {
        return Err("callback_url: at most 2048 characters".into());
    }
    let origin = origin_of(url).map_err(|e| format!("callback_url: {e}"))?;
    let allowed = settings.callback_origins.iter().any(|o| origin_of(o).is_ok_and(|o| o == origin));
    if !allowed {
        return Err(format!(
            "callback_url: {origin} is not among the destinations this server may call (callback_origins{})",
            if settings.callback_origins.is_empty() { ", empty: callbacks are off" } else { "" }
        ));
    }
    if settings.callback_secrets.is_empty() {
        return Err("callback_url: this server has no callback_secrets to sign callbacks with".into());
    }
    Ok(())
}

/// The body of an event: its type, when it happened, and the inspection as `GET
/// /v1/inspections/{id}` shows it.
#[derive(Serialize)]
struct Event<'a> {
    #[serde(rename = "type")]
    type_: &'a str,
    timestamp: String,
    data: Inspection,
}

/// The deliveries an inspection's terminal state makes under `settings`.
fn deliveries_for(settings: &Settings, row: InspectionRow) -> Vec<NewDelivery> {
    let Some(event) = EventType::of_status(&row.status) else { return Vec::new() };
    let callback =
        serde_json::from_str::<crate::service::queue::JobOptions>(&row.options_json).ok().and_then(|o| o.callback_url);
    let timestamp = crate::service::wire::rfc3339(row.finished_at.unwrap_or(row.updated_at));
    let body = Event { type_: event.as_str(), timestamp, data: Inspection::from(row) };
    // As `GET /v1/inspections/{id}` writes it: numbers rounded to their resolution.
    let payload_json =
        String::from_utf8(crate::export::json::to_vec(&body).expect("an event serialises")).expect("JSON is UTF-8");
    let mut targets: Vec<(String, String)> = settings
        .webhooks
        .iter()
        .filter(|e| e.events.contains(&event))
        .map(|e| (e.name.clone(), e.url.clone()))
        .collect();
    if let Some(url) = callback {
        targets.push((CALLBACK.into(), url));
    }
    targets
        .into_iter()
        .map(|(endpoint, url)| NewDelivery {
            id: format!("msg_{}", uuid::Uuid::now_v7().simple()),
            endpoint,
            url,
            event_type: event.as_str().into(),
            payload_json: payload_json.clone(),
        })
        .collect()
}

/// The `station.suspended` deliveries under `settings`: to every endpoint that wants the event
/// (a submission's `callback_url` is about its own inspection, and is not told). `data` is what
/// the event says of the station and the check that suspended it.
pub fn station_deliveries(settings: &Settings, data: &impl Serialize) -> Vec<NewDelivery> {
    #[derive(Serialize)]
    struct StationEvent<'a, T: Serialize> {
        #[serde(rename = "type")]
        type_: &'a str,
        timestamp: String,
        data: &'a T,
    }
    let event = EventType::StationSuspended;
    let body = StationEvent { type_: event.as_str(), timestamp: crate::service::wire::rfc3339(now_ms()), data };
    let payload_json =
        String::from_utf8(crate::export::json::to_vec(&body).expect("an event serialises")).expect("JSON is UTF-8");
    settings
        .webhooks
        .iter()
        .filter(|e| e.events.contains(&event))
        .map(|e| NewDelivery {
            id: format!("msg_{}", uuid::Uuid::now_v7().simple()),
            endpoint: e.name.clone(),
            url: e.url.clone(),
            event_type: event.as_str().into(),
            payload_json: payload_json.clone(),
        })
        .collect()
}

/// Where a delivery goes now and what signs it, under the current settings (an endpoint may have
/// moved or rotated its secrets since the delivery was written); the reason when it may not go.
fn destination(settings: &Settings, delivery: &DeliveryRow) -> Result<(String, Vec<Secret>), String> {
    let parse = |secrets: &[String]| secrets.iter().map(|s| Secret::parse(s)).collect::<Result<Vec<_>, _>>();
    if delivery.endpoint == CALLBACK {
        callback_allowed(settings, &delivery.url)?;
        return Ok((delivery.url.clone(), parse(&settings.callback_secrets)?));
    }
    let endpoint = settings
        .webhooks
        .iter()
        .find(|e| e.name == delivery.endpoint)
        .ok_or_else(|| format!("the endpoint {:?} is no longer configured", delivery.endpoint))?;
    Ok((endpoint.url.clone(), parse(&endpoint.secrets)?))
}

/// The wait before attempt `attempts + 1`: the base doubling per failed attempt up to an hour,
/// scaled by 0.75–1.25 so that many failing deliveries do not return at once. The jitter is drawn
/// from the delivery's id and attempt: the same history gives the same schedule.
pub fn backoff(base_seconds: f64, id: &str, attempts: i64) -> Duration {
    use sha2::Digest;
    let doubled = base_seconds * 2f64.powi((attempts - 1).clamp(0, 30) as i32);
    let digest = sha2::Sha256::digest(format!("{id}/{attempts}").as_bytes());
    let unit = u16::from_le_bytes([digest[0], digest[1]]) as f64 / u16::MAX as f64;
    Duration::from_secs_f64(doubled.min(3600.0) * (0.75 + 0.5 * unit))
}

/// The client deliveries go out with: no redirects, the attempt's time limit, the system's roots.
/// Built at start-up, so that a machine whose certificate store cannot be read refuses to start
/// rather than never delivering.
pub fn client(settings: &Settings) -> Result<reqwest::Client, reqwest::Error> {
    reqwest::Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .timeout(Duration::from_secs_f64(settings.webhook_timeout_seconds))
        .user_agent(concat!("crestscan/", env!("CARGO_PKG_VERSION")))
        .build()
}

/// The dispatcher: announces newly terminal inspections and delivers what is due, until `stop`.
pub async fn run(store: Store, client: reqwest::Client, settings: Arc<Settings>, mut stop: watch::Receiver<bool>) {
    let owner = format!("{}-{}", std::process::id(), uuid::Uuid::now_v7());
    // Long enough for an attempt at its timeout; a process that dies holding one lets it lapse.
    let lease = Duration::from_secs_f64(2.0 * settings.webhook_timeout_seconds + 5.0);
    let poll = Duration::from_millis(settings.poll_interval_ms.max(10));
    // Woken at once when an inspection ends (under PostgreSQL in any process), polling besides.
    let mut changes = store.changes.subscribe();
    loop {
        if *stop.borrow() {
            return;
        }
        if let Err(e) = announce(&store, &settings).await {
            tracing::warn!(error = %e, "webhooks: announcing finished inspections failed");
        }
        match store.claim_deliveries(&owner, lease, 16).await {
            Ok(due) if !due.is_empty() => {
                let attempts = due.into_iter().map(|d| attempt(&store, &client, &settings, &owner, d));
                futures_util::future::join_all(attempts).await;
                continue;
            }
            Ok(_) => {}
            Err(e) => tracing::warn!(error = %e, "webhooks: claiming deliveries failed"),
        }
        let nap = tokio::time::sleep(poll);
        tokio::pin!(nap);
        loop {
            tokio::select! {
                _ = &mut nap => break,
                _ = stop.changed() => break,
                change = changes.recv() => match change {
                    Ok(row) if !row.status().is_terminal() => continue,
                    _ => break,
                },
            }
        }
    }
}

async fn announce(store: &Store, settings: &Settings) -> Result<(), crate::service::store::StoreError> {
    for row in store.unannounced(64).await? {
        let id = row.id.clone();
        let deliveries = deliveries_for(settings, row);
        if store.announce(&id, &deliveries).await? && !deliveries.is_empty() {
            tracing::info!(inspection = %id, deliveries = deliveries.len(), "webhooks: enqueued");
        }
    }
    Ok(())
}

async fn attempt(store: &Store, client: &reqwest::Client, settings: &Settings, owner: &str, delivery: DeliveryRow) {
    let number = delivery.attempts + 1;
    let started_at = now_ms();
    let clock = Instant::now();
    // A destination no longer configured or allowed is given up at once, never contacted.
    let (status_code, error, refused) = match destination(settings, &delivery) {
        Ok((url, secrets)) => {
            let (code, error) = post(client, &url, &secrets, &delivery).await;
            (code, error, false)
        }
        Err(reason) => (None, Some(reason), true),
    };
    let outcome = if error.is_none() {
        AttemptOutcome::Delivered
    } else if refused || number >= settings.webhook_max_attempts as i64 {
        AttemptOutcome::GaveUp
    } else {
        let wait = backoff(settings.webhook_retry_seconds, &delivery.id, number);
        AttemptOutcome::RetryAt(now_ms() + wait.as_millis() as i64)
    };
    let record = AttemptRow {
        delivery_id: delivery.id.clone(),
        attempt: number,
        started_at,
        duration_ms: clock.elapsed().as_millis() as i64,
        status_code,
        error: error.clone(),
    };
    match store.record_attempt(owner, &record, &outcome).await {
        Ok(true) => match (&outcome, &error) {
            (AttemptOutcome::Delivered, _) => {
                tracing::info!(webhook_id = %delivery.id, inspection = %delivery.inspection_id, endpoint = %delivery.endpoint, attempt = number, "webhook delivered")
            }
            (_, Some(error)) => {
                tracing::warn!(webhook_id = %delivery.id, inspection = %delivery.inspection_id, endpoint = %delivery.endpoint, attempt = number, %error, gave_up = outcome == AttemptOutcome::GaveUp, "webhook not delivered")
            }
            _ => {}
        },
        Ok(false) => tracing::warn!(webhook_id = %delivery.id, "webhook lease lapsed; another process has it"),
        Err(e) => {
            tracing::warn!(webhook_id = %delivery.id, error = %e, "webhook attempt not recorded; it will be retried")
        }
    }
}

/// One POST: the status code when an answer came, and the error when it was not a success.
async fn post(
    client: &reqwest::Client,
    url: &str,
    secrets: &[Secret],
    delivery: &DeliveryRow,
) -> (Option<i64>, Option<String>) {
    let timestamp_s = now_ms() / 1000;
    let body = delivery.payload_json.as_bytes().to_vec();
    let sent = client
        .post(url)
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .header("webhook-id", &delivery.id)
        .header("webhook-timestamp", timestamp_s.to_string())
        .header("webhook-signature", signature(secrets, &delivery.id, timestamp_s, &body))
        .body(body)
        .send()
        .await;
    match sent {
        Ok(response) => {
            let status = response.status();
            let code = Some(status.as_u16() as i64);
            if status.is_success() {
                (code, None)
            } else if status.is_redirection() {
                let to = response.headers().get(reqwest::header::LOCATION).and_then(|v| v.to_str().ok()).unwrap_or("?");
                (code, Some(format!("HTTP {status}: redirect to {to} not followed")))
            } else {
                (code, Some(format!("HTTP {status}")))
            }
        }
        Err(e) => {
            use std::error::Error;
            // Without the URL: a callback's query may hold its receiver's token, and this text
            // goes to the log and to the admins' delivery record (which shows the URL apart).
            let e = e.without_url();
            let mut text = e.to_string();
            let mut source = e.source();
            while let Some(s) = source {
                text = format!("{text}: {s}");
                source = s.source();
            }
            (None, Some(text))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn signs_the_standard_webhooks_reference_vector() {
        // The specification's test vector (the reference libraries' own tests use it).
        let secret = Secret::parse("whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw").unwrap();
        let sig = signature(&[secret], "msg_p5jXN8AQM9LWM0D4loKWxJek", 1614265330, br#"{"test": 2432232314}"#);
        assert_eq!(sig, "v1,g0hM9SsE+OTPJTGt/tmIKtSyZlE3uFJELVlNIOLJ1OE=");
    }

    #[test]
    fn every_secret_signs_during_a_rotation() {
        let (a, b) = (Secret::generate().unwrap(), Secret::generate().unwrap());
        let both = signature(&[Secret::parse(&a).unwrap(), Secret::parse(&b).unwrap()], "msg_1", 5, b"{}");
        let one = signature(&[Secret::parse(&b).unwrap()], "msg_1", 5, b"{}");
        assert_eq!(both.split(' ').count(), 2);
        assert!(both.ends_with(&one), "{both} / {one}");
        assert_ne!(signature(&[Secret::parse(&a).unwrap()], "msg_1", 6, b"{}"), both.split(' ').next().unwrap());
    }

    #[test]
    fn event_types_read_back_from_their_names() {
        for e in EventType::ALL {
            assert_eq!(EventType::parse(e.as_str()), Some(e));
            assert_eq!(serde_json::to_value(e).unwrap(), e.as_str());
        }
        assert_eq!(EventType::parse("inspection.queued"), None);
    }

    #[test]
    fn secrets_are_checked() {
        assert!(Secret::parse("MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw").unwrap_err().contains("whsec_"));
        assert!(Secret::parse("whsec_***").unwrap_err().contains("base64"));
        assert!(Secret::parse("whsec_c2hvcnQ=").unwrap_err().contains("24 to 64"));
    }

    #[test]
    fn origins_normalise_and_only_listed_ones_pass() {
        assert_eq!(origin_of("HTTPS://MES.plant.local/hooks?x=1").unwrap(), "https://mes.plant.local:443");
        assert_eq!(origin_of("http://10.0.0.5:8000/a").unwrap(), "http://10.0.0.5:8000");
        assert!(origin_of("ftp://x/").is_err() && origin_of("http://u:p@x/").is_err() && origin_of("x").is_err());
        let settings = Settings {
            callback_origins: vec!["https://mes.plant.local".into(), "http://127.0.0.1:9000".into()],
            callback_secrets: vec![Secret::generate().unwrap()],
            ..Settings::default()
        };
        assert!(callback_allowed(&settings, "https://mes.plant.local:443/in").is_ok());
        assert!(callback_allowed(&settings, "http://127.0.0.1:9000/hook").is_ok());
        for refused in ["http://mes.plant.local/in", "http://127.0.0.1:9001/", "http://169.254.169.254/latest"] {
            let e = callback_allowed(&settings, refused).unwrap_err();
            assert!(e.starts_with("callback_url:") && e.contains("callback_origins"), "{e}");
        }
        assert!(callback_allowed(&Settings::default(), "https://mes.plant.local/").unwrap_err().contains("off"));
    }

    #[test]
    fn back_off_doubles_to_an_hour_with_a_bounded_repeatable_jitter() {
        for attempts in 1..20 {
            let wait = backoff(5.0, "msg_a", attempts).as_secs_f64();
            let nominal = (5.0 * 2f64.powi(attempts as i32 - 1)).min(3600.0);
            assert!((0.75 * nominal..=1.25 * nominal).contains(&wait), "{attempts}: {wait}");
            assert_eq!(backoff(5.0, "msg_a", attempts), backoff(5.0, "msg_a", attempts));
        }
        let spread: std::collections::BTreeSet<u128> =
            (0..20).map(|i| backoff(5.0, &format!("msg_{i}"), 3).as_millis()).collect();
        assert!(spread.len() > 15, "jitter spreads deliveries: {spread:?}");
    }
}
