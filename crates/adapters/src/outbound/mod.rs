//! crispen's outbound HTTP/1.1 (notification receivers, cameras, Spoolman): one connection
//! per request to an [`HttpUrl`], https through rustls with the ring provider and the
//! Mozilla roots (built once), every request with the same Host and User-Agent. One place,
//! so that the three clients connect, speak TLS and name their failures alike.

mod url;
pub use url::{HttpUrl, MAX_URL_CHARS};

use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper_util::rt::TokioIo;
use std::sync::{Arc, OnceLock};
use tokio::net::TcpStream;

/// A connection: plain TCP, or TLS over it.
pub type Io = tokio_util::either::Either<TcpStream, tokio_rustls::client::TlsStream<TcpStream>>;

/// Why a request got no answer.
#[derive(Debug, thiserror::Error)]
pub enum OutboundError {
    #[error("cannot connect to {host}:{port}: {message}")]
    Connect {
        host: String,
        port: u16,
        message: String,
    },
    #[error("TLS with {host}: {message}")]
    Tls { host: String, message: String },
    #[error("HTTP: {0}")]
    Http(String),
    /// The answer's body is larger than the caller's cap (`Cap::Refuse`).
    #[error("an answer larger than {0} bytes")]
    TooLarge(usize),
}

impl OutboundError {
    /// Why no connection was made (TLS included), for a client's own "cannot connect"
    /// error; None for what failed after connecting.
    pub fn connect_failure(&self) -> Option<String> {
        match self {
            OutboundError::Connect { message, .. } => Some(message.clone()),
            OutboundError::Tls { message, .. } => Some(format!("TLS: {message}")),
            OutboundError::Http(_) | OutboundError::TooLarge(_) => None,
        }
    }
}

fn connector() -> tokio_rustls::TlsConnector {
    static CONNECTOR: OnceLock<tokio_rustls::TlsConnector> = OnceLock::new();
    CONNECTOR
        .get_or_init(|| {
            use tokio_rustls::rustls;
            let roots = rustls::RootCertStore {
                roots: webpki_roots::TLS_SERVER_ROOTS.to_vec(),
            };
            let provider = Arc::new(rustls::crypto::ring::default_provider());
            let config = rustls::ClientConfig::builder_with_provider(provider)
                .with_safe_default_protocol_versions()
                .expect("ring supports the default TLS versions")
                .with_root_certificates(roots)
                .with_no_client_auth();
            tokio_rustls::TlsConnector::from(Arc::new(config))
        })
        .clone()
}

/// A connection to `url`'s host, through TLS for https.
pub async fn connect(url: &HttpUrl) -> Result<Io, OutboundError> {
    let tcp = TcpStream::connect((url.host.as_str(), url.port))
        .await
        .map_err(|e| OutboundError::Connect {
            host: url.host.clone(),
            port: url.port,
            message: e.to_string(),
        })?;
    let _ = tcp.set_nodelay(true);
    if !url.https {
        return Ok(tokio_util::either::Either::Left(tcp));
    }
    let tls = |message: String| OutboundError::Tls {
        host: url.host.clone(),
        message,
    };
    let name = tokio_rustls::rustls::pki_types::ServerName::try_from(url.host.clone())
        .map_err(|e| tls(e.to_string()))?;
    let stream = connector()
        .connect(name, tcp)
        .await
        .map_err(|e| tls(e.to_string()))?;
    Ok(tokio_util::either::Either::Right(stream))
}

/// A request for `target` on `url`'s host, with the headers every outbound request has.
pub fn request(
    url: &HttpUrl,
    method: hyper::Method,
    target: &str,
) -> hyper::http::request::Builder {
    hyper::Request::builder()
        .method(method)
        .uri(target)
        .header(hyper::header::HOST, url.host_header())
        .header(
            hyper::header::USER_AGENT,
            concat!("crispen/", env!("CARGO_PKG_VERSION")),
        )
}

/// How much of an answer's body is read.
#[derive(Debug, Clone, Copy)]
pub enum Cap {
    /// An answer larger than this is an error (declared or as it comes).
    Refuse(usize),
    /// Only the start is kept; the rest is not read.
    Cut(usize),
}

/// Sends `request` on a new connection to `url` (`Connection: close`) and reads the answer:
/// its status and body (as `cap` says). The connection is driven here, not by a task of its
/// own, so nothing is left running when the call is dropped at its caller's time limit.
pub async fn send(
    url: &HttpUrl,
    request: hyper::Request<Full<Bytes>>,
    cap: Cap,
) -> Result<(u16, Vec<u8>), OutboundError> {
    let io = connect(url).await?;
    let http = |e: hyper::Error| OutboundError::Http(e.to_string());
    let (mut sender, connection) = hyper::client::conn::http1::handshake(TokioIo::new(io))
        .await
        .map_err(http)?;
    let mut request = request;
    request.headers_mut().insert(
        hyper::header::CONNECTION,
        hyper::header::HeaderValue::from_static("close"),
    );
    let answer = async {
        let response = sender.send_request(request).await.map_err(http)?;
        let status = response.status().as_u16();
        if let Cap::Refuse(max) = cap {
            // A declared length over the cap is refused before any of it is read.
            let declared = response
                .headers()
                .get(hyper::header::CONTENT_LENGTH)
                .and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
            if declared.is_some_and(|n| n > max as u64) {
                return Err(OutboundError::TooLarge(max));
            }
        }
        let mut body = Vec::new();
        let mut stream = response.into_body();
        while let Some(frame) = stream.frame().await {
            let frame = match (frame, cap) {
                (Ok(frame), _) => frame,
                // What was cut is enough: a broken rest does not matter.
                (Err(_), Cap::Cut(_)) => break,
                (Err(e), Cap::Refuse(_)) => return Err(http(e)),
            };
            let Ok(data) = frame.into_data() else {
                continue;
            };
            match cap {
                Cap::Refuse(max) if body.len() + data.len() > max => {
                    return Err(OutboundError::TooLarge(max))
                }
                Cap::Refuse(_) => body.extend_from_slice(&data),
                Cap::Cut(max) => {
                    let room = max.saturating_sub(body.len());
                    body.extend_from_slice(&data[..data.len().min(room)]);
                    if body.len() >= max {
                        break;
                    }
                }
            }
        }
        Ok((status, body))
    };
    tokio::pin!(answer);
    tokio::pin!(connection);
    let mut connection_open = true;
    loop {
        tokio::select! {
            a = &mut answer => return a,
            c = &mut connection, if connection_open => {
                connection_open = false;
                c.map_err(http)?;
            }
        }
    }
}
