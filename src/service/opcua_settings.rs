//! The OPC UA server's settings, checked where the settings are ([`crate::service::config`]): the
//! endpoint's URL (the server itself: [`crate::service::opcua`]).

/// Where the server listens, from `opc.tcp://host:port`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Endpoint {
    pub host: String,
    pub port: u16,
}

impl Endpoint {
    /// Parses the URL; the error says what is wrong. Port 0 takes a free port (the address the
    /// service prints, and `Application::opcua_url`, name the one taken).
    pub fn parse(url: &str) -> Result<Endpoint, String> {
        let parsed =
            reqwest::Url::parse(url).map_err(|e| format!("`{url}` is not a URL ({e}): opc.tcp://host:4840"))?;
        if parsed.scheme() != "opc.tcp" {
            return Err(format!("scheme {:?}: opc.tcp://host:4840", parsed.scheme()));
        }
        let host = parsed.host_str().filter(|h| !h.is_empty()).ok_or("has no host: opc.tcp://host:4840")?;
        if parsed.path().trim_matches('/') != "" || parsed.query().is_some() {
            return Err("takes no path or query: the endpoint is served at its root".into());
        }
        if !parsed.username().is_empty() || parsed.password().is_some() {
            return Err("carries no credentials: clients present an API key as their password".into());
        }
        Ok(Endpoint { host: host.trim_matches(['[', ']']).to_string(), port: parsed.port().unwrap_or(4840) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoint_urls_are_checked() {
        assert_eq!(
            Endpoint::parse("opc.tcp://vision.plant:4841").unwrap(),
            Endpoint { host: "vision.plant".into(), port: 4841 }
        );
        assert_eq!(Endpoint::parse("opc.tcp://127.0.0.1").unwrap().port, 4840);
        assert!(Endpoint::parse("http://host:4840").unwrap_err().contains("scheme"));
        assert!(Endpoint::parse("opc.tcp://host:4840/UA/x").unwrap_err().contains("no path"));
        assert!(Endpoint::parse("opc.tcp://u:p@host").unwrap_err().contains("API key"));
        assert!(Endpoint::parse("host:4840").is_err());
    }
}
