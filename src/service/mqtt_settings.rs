//! The MQTT publisher's settings, checked where the settings are ([`crate::service::config`]):
//! the broker's URL and the topics' site segment (the publisher itself: [`crate::service::mqtt`]).

use std::path::Path;

/// Where the broker is, from `mqtt://host:port` or `mqtts://host:port`.
#[derive(Clone, Debug)]
pub struct Broker {
    pub host: String,
    pub port: u16,
    /// What an `mqtts://` broker's certificate is checked against; None: plain TCP.
    pub tls: Option<Roots>,
}

/// The authorities a broker's certificate is checked against.
#[derive(Clone, Debug, PartialEq)]
pub enum Roots {
    /// The PEM certificates of `mqtt_ca_file`.
    CaFile(Vec<u8>),
    /// The system's (`SSL_CERT_FILE` / `SSL_CERT_DIR` where set, else the system's store).
    System,
}

impl Broker {
    /// Parses the URL (and reads `ca_file` for `mqtts://`); the error says what is wrong.
    pub fn parse(url: &str, ca_file: Option<&Path>) -> Result<Broker, String> {
        let parsed = reqwest::Url::parse(url).map_err(|e| format!("`{url}` is not a URL ({e}): mqtt://host:1883"))?;
        let tls = match parsed.scheme() {
            "mqtt" | "tcp" => false,
            "mqtts" | "ssl" => true,
            other => return Err(format!("scheme {other:?}: mqtt://host:1883 or mqtts://host:8883")),
        };
        let host = parsed.host_str().filter(|h| !h.is_empty()).ok_or("has no host: mqtt://host:1883")?;
        if parsed.path().trim_matches('/') != "" || parsed.query().is_some() {
            return Err("takes no path or query: the topics are crestscan/<mqtt_site>/…".into());
        }
        if !parsed.username().is_empty() || parsed.password().is_some() {
            return Err("carries no credentials: set mqtt_username and mqtt_password".into());
        }
        let tls = match (tls, ca_file) {
            (false, _) => None,
            (true, Some(path)) => {
                Some(Roots::CaFile(std::fs::read(path).map_err(|e| format!("mqtt_ca_file {}: {e}", path.display()))?))
            }
            (true, None) => Some(Roots::System),
        };
        Ok(Broker {
            host: host.trim_matches(['[', ']']).to_string(),
            port: parsed.port().unwrap_or(if tls.is_some() { 8883 } else { 1883 }),
            tls,
        })
    }
}

/// The site segment: 1–64 of `A–Z a–z 0–9 _ -` (no `/`, `+` or `#`, which MQTT reads as levels
/// and wildcards).
pub fn check_site(site: &str) -> Result<(), String> {
    if (1..=64).contains(&site.len()) && site.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-') {
        Ok(())
    } else {
        Err(format!("{site:?}: 1–64 of A–Z a–z 0–9 _ -"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broker_urls_and_sites_are_checked() {
        let b = Broker::parse("mqtt://broker.plant:1884", None).unwrap();
        assert_eq!((b.host.as_str(), b.port, b.tls.is_none()), ("broker.plant", 1884, true));
        assert_eq!(Broker::parse("mqtt://10.0.0.5", None).unwrap().port, 1883);
        let secure = Broker::parse("mqtts://broker", None).unwrap();
        assert_eq!((secure.port, secure.tls), (8883, Some(Roots::System)));
        assert!(
            Broker::parse("mqtts://broker", Some(Path::new("/no/such/ca.pem"))).unwrap_err().contains("mqtt_ca_file")
        );
        assert!(Broker::parse("http://broker", None).unwrap_err().contains("scheme"));
        assert!(Broker::parse("mqtt://u:p@broker", None).unwrap_err().contains("mqtt_username"));
        assert!(Broker::parse("mqtt://broker/topic", None).unwrap_err().contains("no path"));
        assert!(check_site("plant-a_2").is_ok());
        assert!(check_site("plant/a").is_err() && check_site("#").is_err() && check_site("").is_err());
    }
}
