//! The address of an outbound request (a notification receiver, a camera, Spoolman, the
//! dashboard's public address): read by `http::Uri`, as the `http` crate that carries the
//! requests reads a URI, then held split as the client uses it.

/// Longest URL.
pub const MAX_URL_CHARS: usize = 2048;

/// An `http://` or `https://` URL, split as the client needs it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HttpUrl {
    /// As written (shown in logs and by `crispen notify test`).
    pub text: String,
    pub https: bool,
    /// An IPv6 address without its brackets.
    pub host: String,
    pub port: u16,
    /// Path and query, at least "/"; never a fragment.
    pub path: String,
}

impl HttpUrl {
    /// Reads an `http://` or `https://` URL with a host, an optional port and path; no
    /// user or password part (a secret belongs in a secret file, or in the path where the
    /// service puts it, as Slack and Discord do). The error says what is wrong with it.
    pub fn parse(text: &str) -> Result<HttpUrl, String> {
        if text.len() > MAX_URL_CHARS {
            return Err(format!("longer than {MAX_URL_CHARS} characters"));
        }
        if text.chars().any(|c| c.is_whitespace() || c.is_control()) {
            return Err(format!("{text:?} holds spaces or control characters"));
        }
        let not_http = || {
            format!("{text:?} is not an http:// or https:// URL (e.g. \"https://ntfy.sh/my-farm\")")
        };
        let uri: http::Uri = text.parse().map_err(|e: http::uri::InvalidUri| {
            if text.contains("://") {
                format!("{text:?} is not a URL: {e}")
            } else {
                not_http()
            }
        })?;
        let https = match uri.scheme_str() {
            Some("https") => true,
            Some("http") => false,
            _ => return Err(not_http()),
        };
        let Some(authority) = uri.authority() else {
            return Err(format!("{text:?} names no host"));
        };
        if authority.as_str().contains('@') {
            return Err(format!(
                "{text:?} holds a user or password: put a signing secret in secret_file instead"
            ));
        }
        let bracketed = authority.host();
        let host = bracketed
            .strip_prefix('[')
            .and_then(|h| h.strip_suffix(']'))
            .unwrap_or(bracketed);
        if host.is_empty() {
            return Err(format!("{text:?} names no host"));
        }
        // `http::Uri` takes a port it cannot read as none at all; a port written must be
        // one, or the request would go to the scheme's own.
        let written = &authority.as_str()[bracketed.len()..];
        let port = match (written.strip_prefix(':'), authority.port_u16()) {
            (None, _) => {
                if https {
                    443
                } else {
                    80
                }
            }
            (Some(_), Some(p)) if p > 0 => p,
            (Some(p), _) => return Err(format!("{text:?}: {p:?} is not a port (1 to 65535)")),
        };
        let path = match uri.path_and_query().map(|p| p.as_str()) {
            None | Some("") => "/".to_string(),
            Some(p) if p.starts_with('?') => format!("/{p}"),
            Some(p) => p.to_string(),
        };
        Ok(HttpUrl {
            text: text.to_string(),
            https,
            host: host.to_string(),
            port,
            path,
        })
    }

    /// The request's `Host` header: the port only where it is not the scheme's own, an
    /// IPv6 address in brackets (RFC 9110, 7.2).
    pub fn host_header(&self) -> String {
        let host = if self.host.contains(':') {
            format!("[{}]", self.host)
        } else {
            self.host.clone()
        };
        match (self.https, self.port) {
            (true, 443) | (false, 80) => host,
            _ => format!("{host}:{}", self.port),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The port is left out where it is the scheme's own; an IPv6 host is bracketed.
    #[test]
    fn host_headers_name_the_port_only_when_needed() {
        for (url, host) in [
            ("https://ntfy.sh/x", "ntfy.sh"),
            ("http://farm/", "farm"),
            ("http://farm:443/", "farm:443"),
            ("https://farm:8443/", "farm:8443"),
            ("http://[::1]:7912/", "[::1]:7912"),
            ("http://[::1]/", "[::1]"),
        ] {
            assert_eq!(HttpUrl::parse(url).unwrap().host_header(), host, "{url}");
        }
    }

    #[test]
    fn urls_are_split_and_bad_ones_named() {
        let split = |url| {
            let u = HttpUrl::parse(url).unwrap();
            (u.https, u.host, u.port, u.path)
        };
        let owned = |https, host: &str, port, path: &str| (https, host.into(), port, path.into());
        assert_eq!(
            split("https://ntfy.sh/my-farm"),
            owned(true, "ntfy.sh", 443, "/my-farm")
        );
        assert_eq!(
            split("http://127.0.0.1:8123/api/webhook/abc?x=1#frag"),
            owned(false, "127.0.0.1", 8123, "/api/webhook/abc?x=1")
        );
        assert_eq!(split("http://[::1]:9000"), owned(false, "::1", 9000, "/"));
        assert_eq!(split("http://farm?x=1"), owned(false, "farm", 80, "/?x=1"));
        for (bad, says) in [
            ("ftp://x/", "is not an http:// or https:// URL"),
            ("farm/hook", "is not an http:// or https:// URL"),
            ("http://", "is not a URL"),
            ("http://u:p@host/", "user or password"),
            ("http://host:0/", "is not a port"),
            ("http://host:99999/", "is not a port"),
            ("http://host:abc/", "is not a port"),
            ("http://host:/", "is not a port"),
            ("http://:80/", "names no host"),
            ("http://[::1/", "is not a URL"),
            ("http://ho st/", "spaces"),
        ] {
            let e = HttpUrl::parse(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }
}
