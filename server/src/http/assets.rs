//! The pages, scripts and style of the web endpoint, compiled into the binary from
//! `server/static/` (no build step, nothing fetched from elsewhere: they work offline), and the
//! readable 404 page.

use axum::http::{StatusCode, header};
use axum::response::{Html, IntoResponse, Response};

/// The sessions page (`/`).
pub const SESSIONS_PAGE: &str = include_str!("../../static/index.html");
/// The watch page (`/watch/{id}`).
pub const WATCH_PAGE: &str = include_str!("../../static/watch.html");

/// The play page (`/play`, `/play/{id}`).
pub const PLAY_PAGE: &str = include_str!("../../static/play.html");

/// The files under `/static/`: name, content type, content.
const FILES: [(&str, &str, &str); 6] = [
    (
        "style.css",
        "text/css; charset=utf-8",
        include_str!("../../static/style.css"),
    ),
    (
        "common.js",
        "text/javascript; charset=utf-8",
        include_str!("../../static/common.js"),
    ),
    (
        "sessions.js",
        "text/javascript; charset=utf-8",
        include_str!("../../static/sessions.js"),
    ),
    (
        "board.js",
        "text/javascript; charset=utf-8",
        include_str!("../../static/board.js"),
    ),
    (
        "watch.js",
        "text/javascript; charset=utf-8",
        include_str!("../../static/watch.js"),
    ),
    (
        "play.js",
        "text/javascript; charset=utf-8",
        include_str!("../../static/play.js"),
    ),
];

/// An HTML page.
pub fn page(html: &'static str) -> Response {
    Html(html).into_response()
}

/// The file `/static/{name}`, or 404.
pub fn file(name: &str) -> Response {
    match FILES.iter().find(|(n, _, _)| *n == name) {
        Some((_, content_type, text)) => {
            ([(header::CONTENT_TYPE, *content_type)], *text).into_response()
        }
        None => (
            StatusCode::NOT_FOUND,
            Html(not_found_page(
                "Nothing here",
                "This server has no such file.",
            )),
        )
            .into_response(),
    }
}

/// The 404 page of a watch address whose session does not exist.
pub fn not_found(id: &str) -> Response {
    let shown: String = id.chars().take(64).collect();
    let message = format!(
        "There is no session <code>{}</code> on this server: it was closed, it expired after \
         being idle, or the address is mistyped (a watch address needs the full 32-digit ID).",
        escape(&shown)
    );
    (
        StatusCode::NOT_FOUND,
        Html(not_found_page("Session not found", &message)),
    )
        .into_response()
}

/// The 404 page of an address that is no page of this server.
pub fn no_such_page() -> Response {
    (
        StatusCode::NOT_FOUND,
        Html(not_found_page(
            "Nothing here",
            "This address is not a page of this server.",
        )),
    )
        .into_response()
}

/// A small HTML page saying what was not found (`message` is HTML, already escaped).
pub fn not_found_page(title: &str, message: &str) -> String {
    format!(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>{title} · DinerDash</title><link rel=\"icon\" href=\"data:,\">\
         <link rel=\"stylesheet\" href=\"/static/style.css\"></head>\
         <body><header><a class=\"brand\" href=\"/\">DinerDash</a></header>\
         <main class=\"notice\" id=\"not-found\"><h1>{title}</h1><p>{message}</p>\
         <p><a href=\"/\">See the live sessions</a></p></main></body></html>\n"
    )
}

/// `text` safe inside HTML.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_404_page_escapes_what_it_echoes() {
        let r = not_found("<script>alert(1)</script>");
        assert_eq!(r.status(), StatusCode::NOT_FOUND);
        let body = axum::body::to_bytes(r.into_body(), 1 << 20).await.unwrap();
        let body = String::from_utf8(body.to_vec()).unwrap();
        assert!(body.contains("&lt;script&gt;"), "{body}");
        assert!(!body.contains("<script>"));
        assert_eq!(file("board.js").status(), StatusCode::OK);
        assert_eq!(file("../Cargo.toml").status(), StatusCode::NOT_FOUND);
    }
}
