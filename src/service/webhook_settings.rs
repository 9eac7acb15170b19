//! The webhook settings a config file holds (endpoints, the events they want, signing secrets) and
//! the pieces of their validation: a leaf that [`crate::service::config`] imports, so that the
//! settings do not import the dispatcher ([`crate::service::webhooks`]) that reads them.

use base64::Engine;
use base64::engine::general_purpose::STANDARD as BASE64;
use hmac::{Hmac, Mac};
use serde::{Deserialize, Serialize};

/// The events an endpoint can ask for: an inspection's terminal states, and a station suspended
/// by its drift control.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub enum EventType {
    #[serde(rename = "inspection.succeeded")]
    Succeeded,
    #[serde(rename = "inspection.failed")]
    Failed,
    #[serde(rename = "inspection.canceled")]
    Canceled,
    #[serde(rename = "station.suspended")]
    StationSuspended,
}

impl EventType {
    pub const ALL: [EventType; 4] =
        [EventType::Succeeded, EventType::Failed, EventType::Canceled, EventType::StationSuspended];

    pub fn as_str(self) -> &'static str {
        match self {
            EventType::Succeeded => "inspection.succeeded",
            EventType::Failed => "inspection.failed",
            EventType::Canceled => "inspection.canceled",
            EventType::StationSuspended => "station.suspended",
        }
    }

    /// The event type of its name (`inspection.succeeded`, …).
    pub fn parse(name: &str) -> Option<EventType> {
        EventType::ALL.into_iter().find(|e| e.as_str() == name)
    }

    pub(crate) fn of_status(status: &str) -> Option<EventType> {
        match status {
            "succeeded" => Some(EventType::Succeeded),
            "failed" => Some(EventType::Failed),
            "canceled" => Some(EventType::Canceled),
            _ => None,
        }
    }
}

/// An endpoint told of inspections' terminal states and stations' suspensions (a `[[webhooks]]`
/// table of the config file).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EndpointSettings {
    /// Its name in the delivery record: letters, digits, `-` and `_`, 1–64 of them.
    pub name: String,
    /// `http://` or `https://` URL the events are POSTed to.
    pub url: String,
    /// Signing secrets (`whsec_` and base64 of 24–64 random bytes; `crestscan webhook-secret`
    /// makes one). Each signs every delivery: add the new one, move the receiver, drop the old.
    pub secrets: Vec<String>,
    /// The events it wants [default: all four].
    #[serde(default = "all_events")]
    pub events: Vec<EventType>,
}

fn all_events() -> Vec<EventType> {
    EventType::ALL.to_vec()
}

/// The name deliveries to a submission's `callback_url` are recorded under.
pub const CALLBACK: &str = "callback";

/// A signing secret: `whsec_` followed by the base64 of its bytes.
#[derive(Clone)]
pub struct Secret(Vec<u8>);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Secret(<{} bytes>)", self.0.len())
    }
}

impl Secret {
    pub fn parse(text: &str) -> Result<Secret, String> {
        let body = text.trim().strip_prefix("whsec_").ok_or("a webhook secret starts with whsec_")?;
        let bytes = BASE64.decode(body).map_err(|_| "a webhook secret is whsec_ and base64".to_string())?;
        if !(24..=64).contains(&bytes.len()) {
            return Err(format!("a webhook secret holds 24 to 64 bytes; this one {}", bytes.len()));
        }
        Ok(Secret(bytes))
    }

    /// A new secret of 32 random bytes from the operating system.
    pub fn generate() -> Result<String, getrandom::Error> {
        let mut bytes = [0u8; 32];
        getrandom::fill(&mut bytes)?;
        Ok(format!("whsec_{}", BASE64.encode(bytes)))
    }
}

/// The `webhook-signature` header: `v1,<base64 HMAC-SHA256 of "id.timestamp.body">` for each
/// secret, separated by spaces.
pub fn signature(secrets: &[Secret], id: &str, timestamp_s: i64, body: &[u8]) -> String {
    secrets
        .iter()
        .map(|secret| {
            let mut mac = Hmac::<sha2::Sha256>::new_from_slice(&secret.0).expect("HMAC takes a key of any length");
            mac.update(id.as_bytes());
            mac.update(b".");
            mac.update(timestamp_s.to_string().as_bytes());
            mac.update(b".");
            mac.update(body);
            format!("v1,{}", BASE64.encode(mac.finalize().into_bytes()))
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// A URL's origin, `scheme://host:port` (lower-case host, the scheme's port when none is given):
/// what `callback_origins` lists. Only http and https, no user name or password.
pub fn origin_of(url: &str) -> Result<String, String> {
    let parsed = reqwest::Url::parse(url.trim()).map_err(|e| format!("{url:?} is not a URL: {e}"))?;
    if !matches!(parsed.scheme(), "http" | "https") {
        return Err(format!("{url:?}: only http and https URLs"));
    }
    if !parsed.username().is_empty() || parsed.password().is_some() {
        return Err(format!("{url:?}: no user name or password in the URL"));
    }
    let host = parsed.host_str().ok_or_else(|| format!("{url:?} has no host"))?.to_ascii_lowercase();
    let port = parsed.port_or_known_default().expect("http and https have default ports");
    Ok(format!("{}://{host}:{port}", parsed.scheme()))
}
