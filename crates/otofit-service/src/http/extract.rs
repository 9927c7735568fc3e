//! Typed JSON request bodies. A body is read as its route's request struct through
//! `serde_path_to_error`, so a bad field is named by the JSON path serde was at (the
//! path's segments, not the error's text), as a 422 problem; a body that is not JSON is
//! a 400, one of another media type a 415.

use super::Problem;
use axum::body::Bytes;
use axum::extract::{FromRequest, Request};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::de::DeserializeOwned;
use serde_json::error::Category;

/// A JSON request body read as `T` by [`json_body`]; the rejection is its problem.
pub struct JsonBody<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequest<S> for JsonBody<T> {
    type Rejection = Response;

    async fn from_request(req: Request, state: &S) -> Result<Self, Response> {
        let headers = req.headers().clone();
        // A body over the limit or cut short: axum's rejection, made a problem by the
        // `problems` layer (413 names the limit).
        let body = Bytes::from_request(req, state).await.map_err(IntoResponse::into_response)?;
        json_body(&headers, &body).map(JsonBody).map_err(IntoResponse::into_response)
    }
}

/// Parses a JSON body, answering 415 for another content type, 400 for text that is not
/// one JSON value and 422, naming the field, for a value that is not a `T`.
pub fn json_body<T: DeserializeOwned>(headers: &HeaderMap, body: &[u8]) -> Result<T, Problem> {
    let ct = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    // The media type exactly (any case), parameters such as charset allowed.
    let media = ct.split(';').next().unwrap_or("").trim();
    if !media.eq_ignore_ascii_case("application/json") {
        return Err(Problem::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, "send Content-Type: application/json"));
    }
    let mut de = serde_json::Deserializer::from_slice(body);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| match e.inner().classify() {
        Category::Data => {
            let (field, message) = crate::jobs::field_error("", &e);
            Problem::invalid(vec![(if field.is_empty() { "body".into() } else { field }, message)])
        }
        // Where in the text, with the path serde was at: `params.n: expected value at …`.
        Category::Syntax | Category::Eof | Category::Io => malformed(&e),
    })?;
    // Nothing but whitespace after the value.
    de.end().map_err(|e| malformed(&e))?;
    Ok(value)
}

fn malformed(e: &dyn std::fmt::Display) -> Problem {
    Problem::new(StatusCode::BAD_REQUEST, format!("malformed JSON: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::http::infer::InferRequest;
    use crate::http::resources::NewJob;
    use axum::http::HeaderValue;

    fn parse<T: DeserializeOwned>(content_type: &'static str, body: &str) -> Result<T, Problem> {
        let mut headers = HeaderMap::new();
        headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
        json_body(&headers, body.as_bytes())
    }

    /// (status, the one field named or "", message or detail) of a refused body.
    fn refusal<T: DeserializeOwned>(body: &str) -> (u16, String, String) {
        let Err(p) = parse::<T>("application/json; charset=utf-8", body) else { panic!("{body} taken") };
        match &p.errors[..] {
            [] => (p.status, String::new(), p.detail),
            [e] => (p.status, e.field.clone(), e.message.clone()),
            more => panic!("{body}: {more:?}"),
        }
    }

    #[test]
    fn a_bad_field_is_named_by_its_json_path_and_serdes_message() {
        let expected_f64 = "invalid type: string \"x\", expected f64";
        for (body, field, message) in [
            (r#"{}"#, "measurements", "missing field `measurements`"),
            (
                r#"{"measurements": {"impedance": {"frequencies_hz": [1], "magnitude": [1]}}}"#,
                "measurements.impedance.phase",
                "missing field `phase`",
            ),
            (
                r#"{"measurements": {"absorbance": {"frequencies_hz": [1, "x"], "values": []}}}"#,
                "measurements.absorbance.frequencies_hz[1]",
                expected_f64,
            ),
            (r#"{"measurements": {}, "samples": -1}"#, "samples", "invalid value: integer `-1`, expected usize"),
            (r#"{"measurements": {}, "plot": "pie"}"#, "plot", "unknown variant `pie`, expected `corner`"),
            // A value or key that looks like serde's own wording is still the client's.
            (
                r#"{"measurements": {}, "plot": "a: b at line 3"}"#,
                "plot",
                "unknown variant `a: b at line 3`, expected `corner`",
            ),
            ("null", "body", "invalid type: null, expected struct InferRequest"),
            (r#"{"measurements": {}, "measurements": {}}"#, "body", "duplicate field `measurements`"),
            ("[{}]", "[0]", "invalid type: map, expected a string"),
        ] {
            assert_eq!(refusal::<InferRequest>(body), (422, field.into(), message.into()), "{body}");
        }
        // An unknown field is the last step of its path, with the fields serde knows.
        let (status, field, message) = refusal::<InferRequest>(r#"{"measurements": {"wbt": {}, "a: b at line 3": 1}}"#);
        assert_eq!((status, field.as_str()), (422, "measurements.wbt"));
        assert!(message.starts_with("unknown field `wbt`, expected one of `stapes_velocity`"), "{message}");
        let (_, field, message) = refusal::<InferRequest>(r#"{"measurements": {}, "a: b at line 3": 1}"#);
        assert_eq!(field, "a: b at line 3");
        assert!(message.starts_with("unknown field `a: b at line 3`, expected one of `model`"), "{message}");
        assert_eq!(refusal::<NewJob>(r#"{"params": {}}"#), (422, "kind".into(), "missing field `kind`".into()));
    }

    #[test]
    fn text_that_is_not_one_json_value_is_a_400_and_another_media_type_a_415() {
        for (body, detail) in [
            ("", "EOF while parsing a value at line 1 column 0"),
            (r#"{"measurements": }"#, "measurements: expected value at line 1 column 18"),
            (r#"{"measurements": {}}}"#, "trailing characters at line 1 column 21"),
            // serde_json reads an enum from a string or an object only.
            (r#"{"measurements": {}, "posterior": 3}"#, "posterior: expected value at line 1 column 35"),
            (r#"{"measurements": {}, "samples": 1e400}"#, "samples: number out of range at line 1 column 37"),
        ] {
            assert_eq!(refusal::<InferRequest>(body), (400, String::new(), format!("malformed JSON: {detail}")));
        }
        for content_type in ["text/plain", "application/jsonx", ""] {
            let p = parse::<NewJob>(content_type, r#"{"kind": "train"}"#).err().unwrap();
            assert_eq!((p.status, p.detail.as_str()), (415, "send Content-Type: application/json"));
        }
        assert!(parse::<NewJob>("Application/JSON", r#" {"kind": "train"} "#).is_ok());
    }
}
