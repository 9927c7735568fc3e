//! Who is asking: API keys, tenants and the Host guard.
//!
//! A server is *keyed* when it was started with `--api-key-hash` or when `otofit keys add`
//! ever stored a key in its database; then every route but /health needs
//! `Authorization: Bearer <key>`, and the key decides the [`Principal`]: a stored key
//! speaks for its tenant (admin or not), a `--api-key-hash` key for the `default` tenant
//! as an admin (what every key could see before tenants existed). A keyless server (the
//! default for local use) answers everyone as the `default` tenant's admin, but only
//! requests addressed to a loopback name, an IP literal or an `--allowed-host` name
//! (a web page that rebinds its own domain name to 127.0.0.1 sends that name as Host).

use super::{AppState, Problem};
use crate::store::{DEFAULT_TENANT, JobRow, ModelRow, key_hash};
use axum::extract::{Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::sync::atomic::Ordering;
use subtle::ConstantTimeEq;

/// The tenant a request speaks for, and whether it may see every tenant's work.
#[derive(Clone, Debug, PartialEq)]
pub struct Principal {
    /// The tenant whose jobs, datasets and models the request sees.
    pub tenant: String,
    /// Whether the request may see and act on every tenant's work.
    pub admin: bool,
}

impl Principal {
    /// Keyless servers and `--api-key-hash` keys: the `default` tenant, admin.
    pub fn local() -> Principal {
        Principal { tenant: DEFAULT_TENANT.into(), admin: true }
    }

    /// Whether the job (with its dataset, files and params) exists for this principal:
    /// another tenant's job answers 404, as if it did not exist.
    pub fn sees_job(&self, job: &JobRow) -> bool {
        self.admin || job.tenant == self.tenant
    }

    /// Whether the model exists for this principal: its own, the shared ones, or any for
    /// an admin.
    pub fn sees_model(&self, m: &ModelRow) -> bool {
        self.admin || m.tenant.as_deref().is_none_or(|t| t == self.tenant)
    }

    /// The tenant lists are limited to; `None` (all) for an admin.
    pub fn scope(&self) -> Option<&str> {
        (!self.admin).then_some(self.tenant.as_str())
    }
}

/// Whether the server needs keys: `--api-key-hash` keys, or a key in the database. Once
/// keyed, always keyed (keys are revoked, never deleted): the answer is cached. A database
/// error counts as keyed (fail closed).
async fn keyed(st: &AppState) -> bool {
    if !st.key_hashes.is_empty() || st.keyed.load(Ordering::Relaxed) {
        return true;
    }
    let k = st.ctx.store.has_keys().await.unwrap_or(true);
    if k {
        st.keyed.store(true, Ordering::Relaxed);
    }
    k
}

/// The name part of a Host header value: `[::1]:8080` → `::1`, `Example.org:80` →
/// `Example.org`.
fn host_name(value: &str) -> &str {
    match value.strip_prefix('[') {
        Some(rest) => rest.split(']').next().unwrap_or(rest),
        None => value.rsplit_once(':').map_or(value, |(name, _)| name),
    }
}

/// Whether a keyless server may answer a request addressed to `host`: loopback names and
/// IP literals (a DNS-rebinding page always addresses its own domain name), and the
/// names given with `--allowed-host`.
pub fn host_allowed(host: &str, allowed: &[String]) -> bool {
    let name = host_name(host.trim()).trim_end_matches('.').to_ascii_lowercase();
    name == "localhost"
        || name.ends_with(".localhost")
        || name.parse::<std::net::IpAddr>().is_ok()
        || allowed.contains(&name)
}

/// The Host guard of a keyless server: 421 for a request addressed to another name.
/// Requests without a Host header (not from a browser) pass.
fn host_refused(st: &AppState, req: &Request) -> Option<Response> {
    let host = req.headers().get(header::HOST)?;
    let host = host.to_str().unwrap_or("\u{fffd}");
    if host_allowed(host, &st.allowed_hosts) {
        return None;
    }
    let name = host_name(host);
    let detail = format!(
        "this server answers only requests addressed to localhost or an IP address; to serve the host name '{name}', \
         start it with --allowed-host {name} (or with API keys)"
    );
    Some(Problem::new(StatusCode::MISDIRECTED_REQUEST, detail).into_response())
}

/// The principal of a keyed server's request, from its bearer key (the scheme name is
/// case-insensitive, RFC 9110 §11.1).
async fn key_principal(st: &AppState, headers: &axum::http::HeaderMap) -> Result<Option<Principal>, Problem> {
    let key = (headers.get(header::AUTHORIZATION))
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().split_once(' '))
        .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
        .map(|(_, k)| k.trim());
    let Some(key) = key else { return Ok(None) };
    let h = key_hash(key);
    if st.key_hashes.iter().fold(0u8, |acc, stored| acc | stored.ct_eq(&h).unwrap_u8()) == 1 {
        return Ok(Some(Principal::local()));
    }
    // Looked up by its hash: a 256-bit key's hash gives a timing attack nothing to find.
    let owner = st.ctx.store.key_owner(&h).await.map_err(Problem::internal)?;
    Ok(owner.map(|o| Principal { tenant: o.tenant, admin: o.admin }))
}

/// Every request but /health gets its [`Principal`] (a request extension) or a 401; a
/// keyless server's requests pass the Host guard first.
pub async fn guard(State(st): State<AppState>, mut req: Request, next: Next) -> Response {
    let principal = if !keyed(&st).await {
        if let Some(refused) = host_refused(&st, &req) {
            return refused;
        }
        Principal::local()
    } else if req.uri().path() == "/health" {
        return next.run(req).await;
    } else {
        match key_principal(&st, req.headers()).await {
            Ok(Some(p)) => p,
            Ok(None) => {
                let detail = "a valid API key is required (Authorization: Bearer <key>)";
                let mut r = Problem::new(StatusCode::UNAUTHORIZED, detail).into_response();
                r.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
                return r;
            }
            Err(p) => return p.into_response(),
        }
    };
    req.extensions_mut().insert(principal);
    next.run(req).await
}
