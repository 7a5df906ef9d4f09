//! Signed-in users: sessions kept on the server, the cookie that names
//! one, CSRF tokens, the same-origin check of every POST, and the little
//! parsing (cookies, forms) that needs no crate.
//!
//! Sign-in is pasting one's gym access token (the one
//! `gymnasium.make(…, token=…)` and `OFFWORLD_GYM_ACCESS_TOKEN`
//! take). The token stays on the server, in the session table; the
//! browser holds only a random session id in an `HttpOnly`,
//! `SameSite=Strict` cookie, so a page never contains the token and
//! signing out forgets it at once. The table is bounded
//! ([`Sessions::new`]'s `max`: the least recently used session goes
//! first) and a session lapses after `idle` without a request; a restart
//! signs everyone out.
//!
//! Every POST is checked twice against cross-site requests: its `Origin`
//! (or, without one, its `Referer`) must name this host, and its form
//! must carry the session's CSRF token (before sign-in: the token of the
//! sign-in cookie, double-submitted).

use std::collections::HashMap;
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use axum::http::{header, HeaderMap, HeaderValue};
use rand::Rng;

/// The cookie naming a session.
pub const SESSION_COOKIE: &str = "offworld_session";
/// The cookie carrying the sign-in form's CSRF token.
pub const SIGNIN_COOKIE: &str = "offworld_signin";
/// Longest access token accepted (the controller's own limit).
pub const MAX_TOKEN_LEN: usize = 256;

/// A signed-in user, as the handlers see it.
#[derive(Clone)]
pub struct Session {
    /// The session id (the cookie's value).
    pub id: String,
    /// The gym access token: sent to controllers, never into a page.
    pub token: String,
    /// This session's CSRF token (every form's hidden `csrf` field).
    pub csrf: String,
    /// The user's name, as the controller that checked the token said.
    pub user: String,
    /// Whether the user is an operator (the console is theirs).
    pub operator: bool,
    last_used: Instant,
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Session")
            .field("user", &self.user)
            .field("operator", &self.operator)
            .finish_non_exhaustive()
    }
}

/// Every open session, bounded.
pub struct Sessions {
    table: Mutex<HashMap<String, Session>>,
    max: usize,
    idle: Duration,
}

/// A random 256-bit value as 64 hex digits (`rand`'s thread generator:
/// ChaCha seeded from the OS).
pub fn random_token() -> String {
    let bytes: [u8; 32] = rand::rng().random();
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

impl Sessions {
    /// At most `max` sessions, each lapsing after `idle` without use.
    pub fn new(max: usize, idle: Duration) -> Self {
        Self {
            table: Mutex::new(HashMap::new()),
            max: max.max(1),
            idle,
        }
    }

    fn table(&self) -> MutexGuard<'_, HashMap<String, Session>> {
        self.table
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Opens a session for `token`, which a controller said is `user`'s
    /// (an `operator` or not).
    pub fn create(&self, token: String, user: String, operator: bool) -> Session {
        let now = Instant::now();
        let session = Session {
            id: random_token(),
            token,
            csrf: random_token(),
            user,
            operator,
            last_used: now,
        };
        let mut table = self.table();
        table.retain(|_, s| now.duration_since(s.last_used) < self.idle);
        while table.len() >= self.max {
            let Some(oldest) = table
                .values()
                .min_by_key(|s| s.last_used)
                .map(|s| s.id.clone())
            else {
                break;
            };
            table.remove(&oldest);
        }
        table.insert(session.id.clone(), session.clone());
        session
    }

    /// The session named by the request's cookie, if it is open.
    pub fn from_headers(&self, headers: &HeaderMap) -> Option<Session> {
        let id = cookie(headers, SESSION_COOKIE)?;
        let mut table = self.table();
        let now = Instant::now();
        let session = table.get_mut(id)?;
        if now.duration_since(session.last_used) >= self.idle {
            table.remove(id);
            return None;
        }
        session.last_used = now;
        Some(session.clone())
    }

    /// Signs `id` out.
    pub fn remove(&self, id: &str) {
        self.table().remove(id);
    }

    /// Open sessions.
    pub fn len(&self) -> usize {
        self.table().len()
    }

    /// Whether none is open.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The value of cookie `name` in the request, if sent.
pub fn cookie<'a>(headers: &'a HeaderMap, name: &str) -> Option<&'a str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|pair| pair.trim().split_once('='))
        .find(|(k, _)| *k == name)
        .map(|(_, v)| v.trim())
}

/// A `Set-Cookie` value: `HttpOnly`, `SameSite=Strict`, path `/`, kept
/// `max_age_s` (0: deleted); `Secure` when the service is behind TLS.
pub fn set_cookie(name: &str, value: &str, max_age_s: u64, secure: bool) -> HeaderValue {
    let secure = if secure { "; Secure" } else { "" };
    let text =
        format!("{name}={value}; Path=/; HttpOnly; SameSite=Strict; Max-Age={max_age_s}{secure}");
    // Our names and values are ASCII letters, digits and `_`.
    HeaderValue::from_str(&text).unwrap_or_else(|_| HeaderValue::from_static(""))
}

/// Whether two secrets are equal, in time independent of where they differ.
pub fn same_secret(a: &str, b: &str) -> bool {
    a.len() == b.len()
        && a.bytes()
            .zip(b.bytes())
            .fold(0u8, |acc, (x, y)| acc | (x ^ y))
            == 0
}

/// Checks that a POST comes from a page of this service: its `Origin`,
/// or without one its `Referer`, must name the host the request was sent
/// to. Browsers send `Origin` with every form POST (the pages' referrer
/// policy, `same-origin`, keeps it); a request naming neither is refused.
pub fn check_same_origin(headers: &HeaderMap) -> Result<(), String> {
    let host = headers
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .ok_or("the request names no host")?;
    let (what, url) = if let Some(origin) = headers.get(header::ORIGIN) {
        ("origin", origin.to_str().unwrap_or("null"))
    } else if let Some(referer) = headers.get(header::REFERER) {
        ("referer", referer.to_str().unwrap_or(""))
    } else {
        return Err("the request names neither its origin nor its referer".into());
    };
    let authority = url
        .strip_prefix("http://")
        .or_else(|| url.strip_prefix("https://"))
        .map(|rest| rest.split(['/', '?', '#']).next().unwrap_or(""));
    match authority {
        Some(authority) if authority.eq_ignore_ascii_case(host) => Ok(()),
        _ => Err(format!(
            "the request's {what} ({url}) is not this site ({host})"
        )),
    }
}

/// Decodes an `application/x-www-form-urlencoded` body (or a query
/// string): `+` is a space, `%XX` a byte; invalid UTF-8 is replaced.
pub fn parse_form(body: &[u8]) -> Vec<(String, String)> {
    body.split(|&b| b == b'&')
        .filter(|pair| !pair.is_empty())
        .map(|pair| {
            let mut parts = pair.splitn(2, |&b| b == b'=');
            let key = decode(parts.next().unwrap_or_default());
            let value = decode(parts.next().unwrap_or_default());
            (key, value)
        })
        .collect()
}

/// The first value of `name` in a parsed form.
pub fn field<'a>(form: &'a [(String, String)], name: &str) -> Option<&'a str> {
    form.iter()
        .find(|(k, _)| k == name)
        .map(|(_, v)| v.as_str())
}

fn decode(text: &[u8]) -> String {
    let hex = |b: u8| match b {
        b'0'..=b'9' => Some(b - b'0'),
        b'a'..=b'f' => Some(b - b'a' + 10),
        b'A'..=b'F' => Some(b - b'A' + 10),
        _ => None,
    };
    let mut out = Vec::with_capacity(text.len());
    let mut i = 0;
    while i < text.len() {
        match text[i] {
            b'+' => out.push(b' '),
            b'%' if i + 2 < text.len() => match (hex(text[i + 1]), hex(text[i + 2])) {
                (Some(h), Some(l)) => {
                    out.push(h << 4 | l);
                    i += 2;
                }
                _ => out.push(b'%'),
            },
            b => out.push(b),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn forms_decode_plus_percent_and_bad_escapes() {
        let form = parse_form(b"a=1+2&b=%41%2b%zz&c&token=x%3D%26y&d=%4");
        assert_eq!(field(&form, "a"), Some("1 2"));
        assert_eq!(field(&form, "b"), Some("A+%zz"));
        assert_eq!(field(&form, "c"), Some(""));
        assert_eq!(field(&form, "token"), Some("x=&y"));
        assert_eq!(field(&form, "d"), Some("%4"));
        assert_eq!(field(&form, "e"), None);
    }

    #[test]
    fn cookies_are_found_among_others() {
        let mut headers = HeaderMap::new();
        headers.append(header::COOKIE, HeaderValue::from_static("a=1; b=2"));
        headers.append(
            header::COOKIE,
            HeaderValue::from_static("offworld_session=abc"),
        );
        assert_eq!(cookie(&headers, "b"), Some("2"));
        assert_eq!(cookie(&headers, SESSION_COOKIE), Some("abc"));
        assert_eq!(cookie(&headers, "c"), None);
    }

    #[test]
    fn only_this_host_may_post() {
        let with = |pairs: &[(header::HeaderName, &'static str)]| {
            let mut h = HeaderMap::new();
            h.insert(header::HOST, HeaderValue::from_static("lab:8080"));
            for (k, v) in pairs {
                h.insert(k.clone(), HeaderValue::from_static(v));
            }
            check_same_origin(&h)
        };
        assert!(with(&[(header::ORIGIN, "http://lab:8080")]).is_ok());
        assert!(with(&[(header::ORIGIN, "https://LAB:8080")]).is_ok());
        assert!(with(&[(header::REFERER, "http://lab:8080/envs/x?y")]).is_ok());
        assert!(with(&[(header::ORIGIN, "null")]).is_err());
        assert!(with(&[(header::ORIGIN, "http://evil")]).is_err());
        assert!(with(&[(header::ORIGIN, "http://lab:8080.evil")]).is_err());
        assert!(with(&[(header::REFERER, "http://evil/http://lab:8080")]).is_err());
        assert!(with(&[]).is_err());
    }

    #[test]
    fn sessions_are_bounded_and_lapse() {
        let sessions = Sessions::new(2, Duration::from_secs(60));
        let a = sessions.create("token-a".into(), "user-a".into(), false);
        let _b = sessions.create("token-b".into(), "user-b".into(), false);
        let _c = sessions.create("token-c".into(), "user-c".into(), false);
        assert_eq!(sessions.len(), 2);
        let mut headers = HeaderMap::new();
        let cookie = format!("{SESSION_COOKIE}={}", a.id);
        headers.insert(
            header::COOKIE,
            HeaderValue::from_str(&cookie).expect("header"),
        );
        assert!(sessions.from_headers(&headers).is_none(), "a was evicted");
        let lapsing = Sessions::new(2, Duration::ZERO);
        let d = lapsing.create("token-d".into(), "user-d".into(), false);
        let cookie = format!("{SESSION_COOKIE}={}", d.id);
        headers.insert(
            header::COOKIE,
            HeaderValue::from_str(&cookie).expect("header"),
        );
        assert!(lapsing.from_headers(&headers).is_none());
        assert!(same_secret("abc", "abc") && !same_secret("abc", "abd") && !same_secret("a", "ab"));
        assert!(!format!("{d:?}").contains("token-d"));
    }
}
