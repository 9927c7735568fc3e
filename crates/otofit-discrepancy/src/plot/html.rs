//! One self-contained HTML page per run: headings, text, tables and the run's SVG
//! figures (linked by relative name, so the page works in a CLI output folder and when
//! the service serves it beside the figures).

use std::fmt::Write;

enum Block {
    Heading(String),
    Text(String),
    Table(Vec<String>, Vec<Vec<String>>),
    Figure(String, String),
}

/// A report page, built block by block.
pub struct Page {
    title: String,
    blocks: Vec<Block>,
}

/// `s` with the HTML special characters escaped, for text and attribute values.
pub fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

impl Page {
    /// An empty page titled `title`.
    pub fn new(title: &str) -> Page {
        Page { title: title.into(), blocks: Vec::new() }
    }
    /// Appends a section heading.
    pub fn heading(&mut self, s: &str) -> &mut Self {
        self.blocks.push(Block::Heading(s.into()));
        self
    }
    /// Appends a paragraph.
    pub fn text(&mut self, s: &str) -> &mut Self {
        self.blocks.push(Block::Text(s.into()));
        self
    }
    /// Appends a table with a header row.
    pub fn table(&mut self, header: &[&str], rows: Vec<Vec<String>>) -> &mut Self {
        self.blocks.push(Block::Table(header.iter().map(|h| h.to_string()).collect(), rows));
        self
    }
    /// An SVG written beside the page, by file name.
    pub fn figure(&mut self, file: &str, caption: &str) -> &mut Self {
        self.blocks.push(Block::Figure(file.into(), caption.into()));
        self
    }

    /// The whole page as an HTML document.
    pub fn render(&self) -> String {
        let mut h = String::new();
        let _ = write!(
            h,
            "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{t}</title>\n<style>body{{font-family:sans-serif;max-width:980px;margin:2em auto;color:#222}}table{{border-collapse:collapse;margin:1em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}th{{background:#f4f4f4}}td:first-child,th:first-child{{text-align:left}}figure{{margin:1.5em 0}}img{{max-width:100%}}figcaption{{color:#555;font-size:90%}}</style></head><body>\n<h1>{t}</h1>\n",
            t = escape(&self.title)
        );
        for b in &self.blocks {
            match b {
                Block::Heading(s) => {
                    let _ = writeln!(h, "<h2>{}</h2>", escape(s));
                }
                Block::Text(s) => {
                    let _ = writeln!(h, "<p>{}</p>", escape(s));
                }
                Block::Table(head, rows) => {
                    h.push_str("<table><tr>");
                    for c in head {
                        let _ = write!(h, "<th>{}</th>", escape(c));
                    }
                    h.push_str("</tr>\n");
                    for r in rows {
                        h.push_str("<tr>");
                        for c in r {
                            let _ = write!(h, "<td>{}</td>", escape(c));
                        }
                        h.push_str("</tr>\n");
                    }
                    h.push_str("</table>\n");
                }
                Block::Figure(file, caption) => {
                    let _ = writeln!(
                        h,
                        "<figure><a href=\"{f}\"><img src=\"{f}\" alt=\"{c}\"></a><figcaption>{c}</figcaption></figure>",
                        f = escape(file),
                        c = escape(caption)
                    );
                }
            }
        }
        h.push_str("<footer><p><small>otofit ");
        h.push_str(env!("CARGO_PKG_VERSION"));
        h.push_str("</small></p></footer></body></html>\n");
        h
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn page_escapes_text_and_links_figures() {
        let mut p = Page::new("a < b");
        p.text("x & y").table(&["k", "v"], vec![vec!["ρ".into(), "0.9".into()]]).figure("f.svg", "\"quoted\"");
        let h = p.render();
        assert!(h.contains("<h1>a &lt; b</h1>") && h.contains("x &amp; y"));
        assert!(h.contains("<img src=\"f.svg\" alt=\"&quot;quoted&quot;\">"));
        assert_eq!(h.matches("<tr>").count(), 2);
    }
}
