//! How clients reach a coordinator: the URL checks, TLS, the bearer token on every request;
//! and connection failures in words an operator can act on — the whole chain of causes, and
//! for the usual TLS and address mistakes what to change.

use std::error::Error;
use std::time::Duration;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint};
use tonic::{Request, Status};

/// An endpoint for `url` with TLS when it is https.
pub fn endpoint(url: &str, tls_ca: Option<&[u8]>) -> Result<Endpoint, String> {
    if !(url.starts_with("http://") || url.starts_with("https://")) {
        return Err(format!(
            "--coordinator must be an http:// or https:// URL (got {url:?})"
        ));
    }
    let mut ep = Endpoint::from_shared(url.to_string())
        .map_err(|e| format!("--coordinator {url:?} is not a valid URL: {e}"))?
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true);
    if url.starts_with("https://") {
        let mut tls = ClientTlsConfig::new().with_webpki_roots();
        if let Some(ca) = tls_ca {
            tls = tls.ca_certificate(Certificate::from_pem(ca));
        }
        ep = ep
            .tls_config(tls)
            .map_err(|e| format!("TLS configuration: {e}"))?;
    }
    Ok(ep)
}

/// Adds `authorization: Bearer <token>` to every request when a token is set.
#[derive(Clone)]
pub struct Token(pub Option<String>);

impl tonic::service::Interceptor for Token {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(t) = &self.0 {
            let v = format!("Bearer {t}").parse().map_err(|_| {
                Status::invalid_argument("the token holds characters a header cannot")
            })?;
            req.metadata_mut().insert("authorization", v);
        }
        Ok(req)
    }
}

/// `err` and its causes, joined, followed by a hint when the failure matches a known mistake
/// (TLS on one side only, a certificate the client does not trust or that names another
/// host, nothing listening).
pub fn explain_transport(url: &str, err: &(dyn Error + 'static)) -> String {
    let mut parts = vec![err.to_string()];
    let mut cause = err.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !parts.iter().any(|p| p.contains(&text)) {
            parts.push(text);
        }
        cause = c.source();
    }
    let chain = parts.join(": ");
    match hint(url, &chain.to_ascii_lowercase()) {
        Some(h) => format!("{chain} ({h})"),
        None => chain,
    }
}

fn hint(url: &str, chain: &str) -> Option<&'static str> {
    let https = url.starts_with("https://");
    let any = |needles: &[&str]| needles.iter().any(|n| chain.contains(n));
    if any(&["notvalidforname", "not valid for name"]) {
        Some(
            "the coordinator's certificate does not name the host of this URL: use a name it lists",
        )
    } else if any(&[
        "unknownissuer",
        "unknown issuer",
        "invalid peer certificate",
        "certificate verify",
    ]) {
        Some("the coordinator's certificate is not signed by a CA this side trusts: give that CA's PEM with --tls-ca")
    } else if https
        && any(&[
            "invalidcontenttype",
            "corrupt message",
            "wrong version number",
            "invalid content type",
        ])
    {
        Some("the coordinator does not speak TLS on that port: use an http:// URL, or start it with --tls-cert and --tls-key")
    } else if !https
        && any(&[
            "frame with invalid size",
            "h2 protocol error",
            "connection reset",
            "broken pipe",
            "http2 error",
        ])
    {
        Some("if the coordinator serves TLS (--tls-cert), use an https:// URL with --tls-ca")
    } else if any(&["connection refused"]) {
        Some("nothing listens there: is the coordinator running, and on this port?")
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug)]
    struct Chain(&'static str, Option<Box<Chain>>);
    impl std::fmt::Display for Chain {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            f.write_str(self.0)
        }
    }
    impl Error for Chain {
        fn source(&self) -> Option<&(dyn Error + 'static)> {
            self.1.as_deref().map(|c| c as &(dyn Error + 'static))
        }
    }

    #[test]
    fn causes_are_joined_and_tls_mistakes_get_a_hint() {
        let e = Chain(
            "transport error",
            Some(Box::new(Chain(
                "invalid peer certificate: UnknownIssuer",
                None,
            ))),
        );
        let text = explain_transport("https://h:1", &e);
        assert!(
            text.starts_with("transport error: invalid peer certificate"),
            "{text}"
        );
        assert!(text.contains("--tls-ca"), "{text}");
        let plain = Chain("tcp connect error: Connection refused (os error 111)", None);
        assert!(explain_transport("http://h:1", &plain).contains("nothing listens there"));
        let odd = Chain("something else", None);
        assert_eq!(explain_transport("http://h:1", &odd), "something else");
    }
}
