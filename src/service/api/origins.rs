//! Which hosts and origins a browser may reach the service by: the policy the browser guard
//! ([`super::browser`]) applies, from the `allowed_hosts` and `allowed_origins` settings.

/// The host names (beyond IP literals and `localhost`) and the cross-origin origins a service
/// accepts, from the `allowed_hosts` and `allowed_origins` settings, lowercased.
#[derive(Clone, Debug, Default)]
pub struct BrowserPolicy {
    hosts: Vec<String>,
    origins: Vec<String>,
}

impl BrowserPolicy {
    pub fn new(hosts: &[String], origins: &[String]) -> Self {
        let lower = |v: &[String]| v.iter().map(|s| s.trim().trim_end_matches('/').to_ascii_lowercase()).collect();
        Self { hosts: lower(hosts), origins: lower(origins) }
    }

    /// Whether a `Host` value names this service. An IP literal cannot be rebound (the browser
    /// connected to that address for that origin), nor can `localhost`; any other name must be
    /// listed, since a name is what an attacker's DNS points at 127.0.0.1.
    pub fn host_allowed(&self, host: &str) -> bool {
        let name = host_name(host).to_ascii_lowercase();
        name.parse::<std::net::IpAddr>().is_ok()
            || name == "localhost"
            || self.hosts.iter().any(|h| h == "*" || *h == name)
    }

    /// Whether a request carrying `origin` may change state: the same origin as the `Host` it
    /// was sent to, or a listed one. `null` (sandboxed frames, file: pages) never is. The service
    /// speaks plain HTTP, so the same origin is `http://` and the Host; behind a TLS proxy the
    /// `https://` origin is listed in `allowed_origins`.
    pub fn origin_allowed(&self, origin: &str, host: Option<&str>) -> bool {
        let origin = origin.trim().to_ascii_lowercase();
        if origin == "null" {
            return false;
        }
        let same = origin
            .strip_prefix("http://")
            .is_some_and(|authority| host.is_some_and(|h| h.eq_ignore_ascii_case(authority)));
        same || self.origins.iter().any(|o| *o == origin)
    }
}

/// The host part of a `Host` value: `[::1]:8080` → `::1`, `name:8080` → `name`.
fn host_name(host: &str) -> &str {
    if let Some(rest) = host.strip_prefix('[') {
        return rest.split(']').next().unwrap_or(rest);
    }
    host.rsplit_once(':').filter(|(_, port)| port.bytes().all(|b| b.is_ascii_digit())).map_or(host, |(n, _)| n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hosts_are_ip_literals_localhost_or_listed() {
        let none = BrowserPolicy::default();
        for ok in ["127.0.0.1:8080", "127.0.0.1", "[::1]:8080", "localhost:8080", "LOCALHOST", "10.0.0.5:80"] {
            assert!(none.host_allowed(ok), "{ok}");
        }
        for bad in ["evil.example:8080", "evil.example", "127.0.0.1.evil.example", "localhost.evil.example"] {
            assert!(!none.host_allowed(bad), "{bad}");
        }
        let listed = BrowserPolicy::new(&["CrestScan.Plant.Local".into()], &[]);
        assert!(listed.host_allowed("crestscan.plant.local:8080"));
        assert!(!listed.host_allowed("other.plant.local"));
    }

    #[test]
    fn origins_are_the_same_one_or_listed_and_never_null() {
        let policy = BrowserPolicy::new(&[], &["https://mes.plant.local/".into()]);
        assert!(policy.origin_allowed("http://127.0.0.1:8080", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("http://127.0.0.1:9999", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("http://evil.example", Some("127.0.0.1:8080")));
        assert!(policy.origin_allowed("https://mes.plant.local", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("null", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("http://127.0.0.1:8080", None));
        // The service is plain HTTP: an https origin with the same authority is another origin.
        assert!(!policy.origin_allowed("https://127.0.0.1:8080", Some("127.0.0.1:8080")));
        assert!(!policy.origin_allowed("ftp://127.0.0.1:8080", Some("127.0.0.1:8080")));
    }
}
