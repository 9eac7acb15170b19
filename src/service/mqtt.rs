//! MQTT events (`mqtt_url`; docs/interchange.md, "MQTT events"): every status an inspection takes,
//! each succeeded inspection's result summary, and each station's status, published as JSON with
//! QoS 1 to
//!
//! - `crestscan/<site>/inspections/<id>/state`: `{event_id, inspection_id, status, at, link}`;
//! - `crestscan/<site>/inspections/<id>/result` (once succeeded): `{event_id, inspection_id,
//!   verdict, decision, review_required, station, serial, connection, report}`;
//! - `crestscan/<site>/stations/<name>/status`, retained (a subscriber that comes later reads the
//!   station's last status at once): `{event_id, station, status, reason, at}`.
//!
//! The events come from the database's `events` table, which triggers fill in the transaction that
//! changes a status, so none is missed whichever process made it. One process at a time publishes
//! (a lease on the cursor's row), in `seq` order, one message in flight, and moves its cursor only
//! after the broker's PUBACK: the broker going away never blocks or loses an inspection; what it
//! missed is delivered when it returns. Delivery is at least once: a message repeated after a
//! reconnect carries the same `event_id`.

use crate::service::config::Settings;
pub use crate::service::mqtt_settings::{Broker, Roots, check_site};
use crate::service::store::{EventRow, Store, StoreError};
use crate::service::wire::rfc3339;
use rumqttc::{AsyncClient, Event, EventLoop, MqttOptions, Packet, QoS, Transport};
use serde_json::json;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::watch;

/// The publisher's lease on the cursor: renewed every batch; another process takes over after it
/// lapses.
const LEASE: Duration = Duration::from_secs(30);
/// How long one message waits for its PUBACK before the connection is taken as broken.
const ACK_TIMEOUT: Duration = Duration::from_secs(10);
/// Events read at a time.
const BATCH: i64 = 100;

/// One message to publish.
#[derive(Clone, Debug, PartialEq)]
pub struct Message {
    pub topic: String,
    pub payload: String,
    pub retain: bool,
}

/// The messages an event makes (module docs). A record that cannot be read now is an error (the
/// event is tried again), never a message left out.
pub async fn messages(store: &Store, site: &str, event: &EventRow) -> Result<Vec<Message>, StoreError> {
    let at = rfc3339(event.at);
    match event.subject_kind.as_str() {
        "inspection" => {
            let id = &event.subject;
            let mut out = vec![Message {
                topic: format!("crestscan/{site}/inspections/{id}/state"),
                payload: json!({
                    "event_id": event.seq,
                    "inspection_id": id,
                    "status": event.status,
                    "at": at,
                    "link": format!("/v1/inspections/{id}"),
                })
                .to_string(),
                retain: false,
            }];
            // Only a succeeded inspection's event reads its row, for the result.
            let row = match event.status.as_str() {
                "succeeded" => match store.inspection(id).await {
                    Ok(row) => Some(row),
                    Err(StoreError::NotFound) => None,
                    Err(e) => return Err(e),
                },
                _ => None,
            };
            if let Some(row) = row {
                out.push(Message {
                    topic: format!("crestscan/{site}/inspections/{id}/result"),
                    payload: json!({
                        "event_id": event.seq,
                        "inspection_id": id,
                        "verdict": row.verdict,
                        "decision": row.decision,
                        "review_required": row.review_required,
                        "station": row.station,
                        "serial": row.serial,
                        "connection": row.connection,
                        "at": at,
                        "report": format!("/v1/inspections/{id}/report"),
                    })
                    .to_string(),
                    retain: false,
                });
            }
            Ok(out)
        }
        _ => {
            let reason = match store.station(&event.subject).await {
                Ok(station) => station.status_reason,
                Err(StoreError::NotFound) => None,
                Err(e) => return Err(e),
            };
            Ok(vec![Message {
                topic: format!("crestscan/{site}/stations/{}/status", event.subject),
                payload: json!({
                    "event_id": event.seq,
                    "station": event.subject,
                    "status": event.status,
                    "reason": reason,
                    "at": at,
                })
                .to_string(),
                retain: true,
            }])
        }
    }
}

/// The system's roots (`SSL_CERT_FILE` / `SSL_CERT_DIR` where set), read at each connection so a
/// renewed store is taken; what cannot be read is logged, and with no root at all the broker's
/// certificate fails its check (logged at each try) rather than being trusted.
fn system_roots() -> rumqttc::TlsConfiguration {
    use rumqttc::tokio_rustls::rustls::{ClientConfig, RootCertStore};
    let found = rustls_native_certs::load_native_certs();
    for e in &found.errors {
        tracing::warn!(error = %e, "MQTT: a system certificate store could not be read");
    }
    let mut roots = RootCertStore::empty();
    let (added, ignored) = roots.add_parsable_certificates(found.certs);
    if ignored > 0 {
        tracing::warn!(ignored, "MQTT: system certificates that do not parse were left out");
    }
    if added == 0 {
        tracing::warn!("MQTT: no system roots; an mqtts:// broker cannot be checked (set mqtt_ca_file)");
    }
    let config = ClientConfig::builder().with_root_certificates(roots).with_no_client_auth();
    rumqttc::TlsConfiguration::Rustls(Arc::new(config))
}

/// A connection to the broker: the client and the event loop that drives it.
struct Connection {
    client: AsyncClient,
    events: EventLoop,
}

impl Connection {
    fn open(broker: &Broker, settings: &Settings, client_id: &str) -> Connection {
        let mut options = MqttOptions::new(client_id, &broker.host, broker.port);
        options.set_keep_alive(Duration::from_secs(30));
        options.set_clean_session(true);
        if let (Some(user), Some(password)) = (&settings.mqtt_username, &settings.mqtt_password) {
            options.set_credentials(user, password);
        }
        match &broker.tls {
            Some(Roots::CaFile(ca)) => options.set_transport(Transport::tls(ca.clone(), None, None)),
            Some(Roots::System) => options.set_transport(Transport::tls_with_config(system_roots())),
            None => &mut options,
        };
        let (client, events) = AsyncClient::new(options, 16);
        Connection { client, events }
    }

    /// Publishes one message and waits for the broker's PUBACK.
    async fn publish(&mut self, message: &Message) -> Result<(), String> {
        self.client
            .publish(&message.topic, QoS::AtLeastOnce, message.retain, message.payload.clone())
            .await
            .map_err(|e| e.to_string())?;
        let acked = async {
            loop {
                match self.events.poll().await {
                    Ok(Event::Incoming(Packet::PubAck(_))) => return Ok(()),
                    Ok(_) => {}
                    Err(e) => return Err(e.to_string()),
                }
            }
        };
        tokio::time::timeout(ACK_TIMEOUT, acked)
            .await
            .map_err(|_| format!("no acknowledgement within {} s", ACK_TIMEOUT.as_secs()))?
    }
}

/// Publishes events until `stop` turns true (module docs). Runs in every process that has
/// `mqtt_url`; the lease makes one of them the publisher.
pub async fn run(store: Store, settings: Arc<Settings>, mut stop: watch::Receiver<bool>) {
    let Some(url) = settings.mqtt_url.clone() else { return };
    let broker = match Broker::parse(&url, settings.mqtt_ca_file.as_deref()) {
        Ok(b) => b,
        Err(e) => {
            tracing::error!(error = %e, "mqtt_url: not publishing");
            return;
        }
    };
    let owner = format!("crestscan-{}", uuid::Uuid::now_v7().simple());
    let poll = Duration::from_millis(settings.poll_interval_ms.max(50));
    let mut changes = store.changes.subscribe();
    let mut connection: Option<Connection> = None;
    let mut backoff = Duration::from_millis(500);
    tracing::info!(broker = %format!("{}:{}", broker.host, broker.port), site = %settings.mqtt_site, "MQTT events on");
    'outer: while !*stop.borrow() {
        let cursor = match store.mqtt_lease(&owner, LEASE).await {
            Ok(Some(cursor)) => Some(cursor),
            Ok(None) => None,
            Err(e) => {
                tracing::warn!(error = %e, "MQTT publisher: reading the cursor");
                None
            }
        };
        let events = match cursor {
            Some(cursor) => store.events_after(cursor, BATCH).await.unwrap_or_else(|e| {
                tracing::warn!(error = %e, "MQTT publisher: reading events");
                Vec::new()
            }),
            None => Vec::new(),
        };
        if events.is_empty() {
            // Woken by a change this process sees (under PostgreSQL, any process's), else polled.
            tokio::select! {
                _ = changes.recv() => {}
                _ = tokio::time::sleep(poll) => {}
                _ = stop.changed() => {}
            }
            continue;
        }
        for event in &events {
            let conn = connection.get_or_insert_with(|| Connection::open(&broker, &settings, &owner));
            let messages = match messages(&store, &settings.mqtt_site, event).await {
                Ok(messages) => messages,
                Err(e) => {
                    tracing::warn!(error = %e, event = event.seq, "MQTT publisher: reading the event's record");
                    tokio::select! {
                        _ = tokio::time::sleep(poll) => {}
                        _ = stop.changed() => {}
                    }
                    continue 'outer;
                }
            };
            for message in messages {
                if let Err(e) = conn.publish(&message).await {
                    tracing::warn!(error = %e, topic = %message.topic, retry_in_ms = backoff.as_millis() as u64,
                        "MQTT broker unreachable; events wait for it");
                    connection = None;
                    tokio::select! {
                        _ = tokio::time::sleep(backoff) => {}
                        _ = stop.changed() => {}
                    }
                    backoff = (backoff * 2).min(Duration::from_secs(30));
                    continue 'outer;
                }
            }
            backoff = Duration::from_millis(500);
            match store.mqtt_delivered(&owner, event.seq).await {
                Ok(true) => {}
                // The lease lapsed (a stall longer than it): another process goes on from the cursor.
                Ok(false) => continue 'outer,
                Err(e) => {
                    tracing::warn!(error = %e, "MQTT publisher: moving the cursor");
                    continue 'outer;
                }
            }
        }
    }
    if let Some(conn) = connection {
        let _ = conn.client.disconnect().await;
    }
    let _ = store.mqtt_release(&owner).await;
}
