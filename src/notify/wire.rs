//! One attempt to send one event to one receiver: the body in the receiver's format, its
//! HMAC-SHA256 signature when the receiver has a secret, and an HTTP/1.1 POST (over TLS
//! for `https://`, with the Mozilla roots of `webpki-roots`), all within the receiver's
//! `timeout_s`. The connection is one per attempt and closed after it: events are rare.

use super::event::Event;
use crate::daemon::config::notify::{NotifyFormat, Receiver};
use bytes::Bytes;
use http_body_util::Full;
use std::time::Duration;

/// The part of an answer kept (shown by `crispen notify test`, logged on a failure).
pub(crate) const MAX_ANSWER_BYTES: usize = 4096;
/// Discord refuses longer messages.
const DISCORD_MAX_CHARS: usize = 2000;

/// What a receiver answered.
#[derive(Debug, Clone, PartialEq)]
pub struct Answer {
    pub status: u16,
    /// The start of the answer's body, as text.
    pub body: String,
}

impl Answer {
    pub fn ok(&self) -> bool {
        (200..300).contains(&self.status)
    }

    /// An answer that will not change on a retry (a wrong URL, a refused body): the
    /// event is dropped at once. Timeouts (408), rate limits (429) and server errors are
    /// retried.
    pub(crate) fn permanent(&self) -> bool {
        (400..500).contains(&self.status) && self.status != 408 && self.status != 429
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// Connecting, TLS or HTTP failed.
    #[error(transparent)]
    Outbound(#[from] crate::outbound::OutboundError),
    #[error("HTTP: {0}")]
    Http(String),
    #[error("no answer within {0:?}")]
    Timeout(Duration),
}

/// The body and headers of `event` for `receiver`.
pub(crate) fn render(receiver: &Receiver, event: &Event) -> (Vec<u8>, Vec<(&'static str, String)>) {
    let mut headers = vec![
        ("x-crispen-event", event.event.name().to_string()),
        ("x-crispen-id", event.id.clone()),
    ];
    let body = match receiver.format {
        NotifyFormat::Json => {
            headers.push(("content-type", "application/json".into()));
            serde_json::to_vec(event).unwrap_or_default()
        }
        NotifyFormat::Ntfy => {
            // ntfy reads the message from the body and the rest from headers (see
            // docs.ntfy.sh, "Publishing"); header values must be plain ASCII.
            headers.push(("content-type", "text/plain; charset=utf-8".into()));
            headers.push(("title", event.event.title().into()));
            let (priority, tag) = if event.event.urgent() {
                ("high", "warning")
            } else {
                ("default", "white_check_mark")
            };
            headers.push(("priority", priority.into()));
            headers.push(("tags", format!("{tag},crispen")));
            if let Some(link) = &event.link {
                headers.push(("click", link.clone()));
            }
            // ntfy shows an attachment given by its URL under the message.
            if let Some(picture) = &event.snapshot {
                headers.push(("attach", picture.clone()));
                headers.push(("filename", "snapshot.jpg".into()));
            }
            event.text().into_bytes()
        }
        NotifyFormat::Slack => {
            headers.push(("content-type", "application/json".into()));
            // Slack's text is its mrkdwn: &, < and > are escaped; a link is <url|text>.
            let mut text = slack_escape(&event.text());
            if let Some(link) = &event.link {
                text += &format!(" <{}|dashboard>", slack_escape(link));
            }
            let mut body = serde_json::json!({ "text": text });
            if let Some(picture) = &event.snapshot {
                // The text stays the notification's; the picture is a block under it.
                body["blocks"] = serde_json::json!([
                    { "type": "section", "text": { "type": "mrkdwn", "text": text } },
                    { "type": "image", "image_url": picture, "alt_text": "the printer's camera" },
                ]);
            }
            serde_json::to_vec(&body).unwrap_or_default()
        }
        NotifyFormat::Discord => {
            headers.push(("content-type", "application/json".into()));
            let mut text = event.text();
            if let Some(link) = &event.link {
                text += &format!(" {link}");
            }
            let text: String = text.chars().take(DISCORD_MAX_CHARS).collect();
            // A file named "@everyone" must not ping a whole server.
            let mut body = serde_json::json!({
                "content": text,
                "allowed_mentions": { "parse": [] },
            });
            if let Some(picture) = &event.snapshot {
                body["embeds"] = serde_json::json!([{ "image": { "url": picture } }]);
            }
            serde_json::to_vec(&body).unwrap_or_default()
        }
    };
    if let Some(secret) = &receiver.secret {
        headers.push((
            "x-crispen-signature",
            format!("sha256={}", sign(&secret.0, &body)),
        ));
    }
    (body, headers)
}

fn slack_escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// HMAC-SHA256 of `body` with `secret`, in lower-case hex.
pub(crate) fn sign(secret: &[u8], body: &[u8]) -> String {
    use hmac::{KeyInit, Mac};
    let mut mac =
        hmac::Hmac::<sha2::Sha256>::new_from_slice(secret).expect("HMAC takes a key of any length");
    mac.update(body);
    mac.finalize()
        .into_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Sends `event` to `receiver` once, within its timeout.
pub async fn send(receiver: &Receiver, event: &Event) -> Result<Answer, SendError> {
    let (body, headers) = render(receiver, event);
    tokio::time::timeout(receiver.timeout, exchange(receiver, body, headers))
        .await
        .map_err(|_| SendError::Timeout(receiver.timeout))?
}

async fn exchange(
    receiver: &Receiver,
    body: Vec<u8>,
    headers: Vec<(&'static str, String)>,
) -> Result<Answer, SendError> {
    let url = &receiver.url;
    let mut request = crate::outbound::request(url, hyper::Method::POST, &url.path);
    for (name, value) in headers {
        request = request.header(name, value);
    }
    let request = request
        .body(Full::new(Bytes::from(body)))
        .map_err(|e| SendError::Http(e.to_string()))?;
    // Only the start of the body is kept; a longer one is cut, not an error.
    let (status, body) =
        crate::outbound::send(url, request, crate::outbound::Cap::Cut(MAX_ANSWER_BYTES)).await?;
    Ok(Answer {
        status,
        body: String::from_utf8_lossy(&body).into_owned(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::config::notify::NotifySecret;
    use crate::notify::event::EventKind;
    use crate::outbound::HttpUrl;

    fn receiver(format: NotifyFormat) -> Receiver {
        Receiver {
            name: "r".into(),
            url: HttpUrl::parse("http://127.0.0.1:1/hook").unwrap(),
            events: vec![],
            format,
            secret_file: None,
            secret: Some(NotifySecret(b"key".to_vec())),
            timeout: Duration::from_secs(1),
            retry_for: Duration::from_secs(60),
            max_attempts: 3,
            backoff_max: Duration::from_secs(1),
        }
    }

    /// A camera's snapshot goes with the message: ntfy's attachment, Slack's image block,
    /// Discord's embedded image, the JSON's `snapshot`.
    #[test]
    fn snapshots_go_as_each_receiver_shows_pictures() {
        let mut e = Event::new(EventKind::JobDone, 10.0, "h");
        e.snapshot = Some("http://farm/api/v1/jobs/j/camera/end.jpg".into());
        let url = e.snapshot.clone().unwrap();
        let (_, headers) = render(&receiver(NotifyFormat::Ntfy), &e);
        assert!(headers.contains(&("attach", url.clone())), "{headers:?}");
        let (body, _) = render(&receiver(NotifyFormat::Slack), &e);
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["blocks"][1]["image_url"], url.as_str(), "{v}");
        assert!(v["text"].is_string());
        let (body, _) = render(&receiver(NotifyFormat::Discord), &e);
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["embeds"][0]["image"]["url"], url.as_str(), "{v}");
        let (body, _) = render(&receiver(NotifyFormat::Json), &e);
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["snapshot"], url.as_str(), "{v}");
        // Without a camera, nothing is added.
        e.snapshot = None;
        let (body, _) = render(&receiver(NotifyFormat::Discord), &e);
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert!(v.get("embeds").is_none(), "{v}");
    }

    /// The signature is RFC 4231's HMAC-SHA256, over the exact body sent, in every format.
    #[test]
    fn bodies_are_signed_as_sent() {
        // RFC 4231, test case 2.
        assert_eq!(
            sign(b"Jefe", b"what do ya want for nothing?"),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        let mut e = Event::new(EventKind::JobFailed, 10.0, "h");
        e.reason = Some("<@everyone> & friends".into());
        e.link = Some("http://farm:8080".into());
        for format in [
            NotifyFormat::Json,
            NotifyFormat::Ntfy,
            NotifyFormat::Slack,
            NotifyFormat::Discord,
        ] {
            let (body, headers) = render(&receiver(format), &e);
            let signature = headers
                .iter()
                .find(|(k, _)| *k == "x-crispen-signature")
                .unwrap();
            assert_eq!(signature.1, format!("sha256={}", sign(b"key", &body)));
            assert!(headers
                .iter()
                .any(|(k, v)| *k == "x-crispen-id" && *v == e.id));
        }
        let (body, _) = render(&receiver(NotifyFormat::Slack), &e);
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        let text = v["text"].as_str().unwrap();
        assert!(text.contains("&lt;@everyone&gt; &amp; friends"), "{text}");
        assert!(text.ends_with("<http://farm:8080|dashboard>"), "{text}");
        let (body, _) = render(&receiver(NotifyFormat::Json), &e);
        let back: Event = serde_json::from_slice(&body).unwrap();
        assert_eq!(back, e);
    }
}
