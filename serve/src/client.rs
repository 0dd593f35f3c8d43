//! A minimal HTTP client of the endpoint: `lightrig stop --url` and the tests. One request per
//! connection, as the endpoint serves them.

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::Duration;

/// An endpoint's address: `http://HOST:PORT/` (a path and `?token=` are allowed and the token
/// taken from it).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Endpoint {
    /// `HOST:PORT`.
    pub authority: String,
    pub token: Option<String>,
}

impl Endpoint {
    /// Parses `url`; `token` given apart wins over one in the URL.
    pub fn parse(url: &str, token: Option<&str>) -> Result<Endpoint, String> {
        let rest = url.strip_prefix("http://").ok_or_else(|| {
            format!("{url}: the endpoint's address starts with http:// (as its run printed it)")
        })?;
        let (authority, tail) = rest.split_once('/').unwrap_or((rest, ""));
        if authority.is_empty() {
            return Err(format!("{url}: no host"));
        }
        let authority = if authority.rsplit_once(':').is_some_and(|(_, p)| p.parse::<u16>().is_ok()) {
            authority.to_string()
        } else {
            format!("{authority}:80")
        };
        let in_url = tail
            .split_once('?')
            .map(|(_, q)| q)
            .into_iter()
            .flat_map(|q| q.split('&'))
            .find_map(|kv| kv.strip_prefix("token="))
            .map(str::to_string);
        Ok(Endpoint { authority, token: token.map(str::to_string).or(in_url) })
    }

    /// Sends `method path` with `body` (JSON if any); the status and the answer's body.
    pub fn request(
        &self,
        method: &str,
        path: &str,
        body: Option<&str>,
        timeout: Duration,
    ) -> Result<(u16, Vec<u8>), String> {
        let addr = self
            .authority
            .to_socket_addrs()
            .map_err(|e| format!("{}: {e}", self.authority))?
            .next()
            .ok_or_else(|| format!("{}: no address", self.authority))?;
        let mut s = TcpStream::connect_timeout(&addr, timeout).map_err(|e| {
            format!("{}: {e} (is the run serving? it prints `live: http://…` at start)", self.authority)
        })?;
        s.set_read_timeout(Some(timeout)).map_err(|e| e.to_string())?;
        s.set_write_timeout(Some(timeout)).map_err(|e| e.to_string())?;
        let auth = self.token.as_ref().map(|t| format!("Authorization: Bearer {t}\r\n")).unwrap_or_default();
        let body = body.unwrap_or("");
        let head = format!(
            "{method} {path} HTTP/1.1\r\nHost: {}\r\n{auth}Content-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            self.authority,
            body.len()
        );
        s.write_all(head.as_bytes()).and_then(|_| s.write_all(body.as_bytes())).map_err(|e| e.to_string())?;
        // To its Content-Length (a server may keep the connection open), else to the end.
        let mut answer = Vec::new();
        let mut chunk = [0u8; 8192];
        loop {
            if let Some(whole) = answer_length(&answer) {
                if answer.len() >= whole {
                    break;
                }
            }
            match s.read(&mut chunk) {
                Ok(0) => break,
                Ok(n) => answer.extend_from_slice(&chunk[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(format!("{}: reading the answer: {e}", self.authority)),
            }
        }
        parse_answer(&answer).ok_or_else(|| format!("{}: not an HTTP answer", self.authority))
    }

    /// `GET path`, its body as JSON.
    pub fn get_json(&self, path: &str) -> Result<(u16, serde_json::Value), String> {
        let (status, body) = self.request("GET", path, None, Duration::from_secs(10))?;
        let v = serde_json::from_slice(&body).map_err(|e| format!("{path}: answer is not JSON: {e}"))?;
        Ok((status, v))
    }

    /// `POST path`, its answer as JSON.
    pub fn post_json(&self, path: &str) -> Result<(u16, serde_json::Value), String> {
        let (status, body) = self.request("POST", path, Some("{}"), Duration::from_secs(10))?;
        let v = serde_json::from_slice(&body).map_err(|e| format!("{path}: answer is not JSON: {e}"))?;
        Ok((status, v))
    }
}

/// The length of the whole answer (head and body) once its head is in, if it says.
fn answer_length(bytes: &[u8]) -> Option<usize> {
    let end = bytes.windows(4).position(|w| w == b"\r\n\r\n")? + 4;
    let mut headers = [httparse::EMPTY_HEADER; 32];
    let mut r = httparse::Response::new(&mut headers);
    r.parse(&bytes[..end]).ok()?;
    let len = r.headers.iter().find(|h| h.name.eq_ignore_ascii_case("content-length"))?;
    Some(end + std::str::from_utf8(len.value).ok()?.trim().parse::<usize>().ok()?)
}

/// The status and body of a whole HTTP answer (`Content-Length` or to the end).
pub fn parse_answer(bytes: &[u8]) -> Option<(u16, Vec<u8>)> {
    let end = bytes.windows(4).position(|w| w == b"\r\n\r\n")? + 4;
    let mut headers = [httparse::EMPTY_HEADER; 32];
    let mut r = httparse::Response::new(&mut headers);
    r.parse(&bytes[..end]).ok()?;
    let len = r
        .headers
        .iter()
        .find(|h| h.name.eq_ignore_ascii_case("content-length"))
        .and_then(|h| std::str::from_utf8(h.value).ok()?.trim().parse::<usize>().ok());
    let body = &bytes[end..];
    Some((r.code?, body[..len.unwrap_or(body.len()).min(body.len())].to_vec()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_address_gives_its_authority_and_token() {
        let e = Endpoint::parse("http://127.0.0.1:7878/?token=abc", None).unwrap();
        assert_eq!(e, Endpoint { authority: "127.0.0.1:7878".into(), token: Some("abc".into()) });
        let e = Endpoint::parse("http://rig-pc", Some("t2")).unwrap();
        assert_eq!(e, Endpoint { authority: "rig-pc:80".into(), token: Some("t2".into()) });
        assert!(Endpoint::parse("rig-pc:7878", None).unwrap_err().contains("starts with http://"));
    }
}
