//! otofit: subject-specific middle-ear finite-element models tuned by neural posterior
//! estimation.
//!
//! The numerical core (`sim`, `flow`, `npe`) is synchronous, takes plain data plus a
//! config, and knows nothing of HTTP or SQL. `cli` holds the command-line glue.
#![warn(missing_docs)]

pub mod artifacts;
pub mod bench;
pub mod cli;
pub mod dataset;
pub mod discrepancy;
pub mod flow;
pub mod formats;
pub mod gate;
pub mod http;
pub mod jobs;
pub mod measurements;
pub mod metrics;
pub mod npe;
pub mod plot;
pub mod reference;
pub mod sim;
pub mod stats;
pub mod store;

#[cfg(test)]
mod layers {
    /// The pipeline, lowest first: a module may use those before it, never those after.
    const PIPELINE: [&str; 8] = ["sim", "flow", "npe", "discrepancy", "plot", "jobs", "http", "cli"];
    /// Modules beside the pipeline: they may use the numerical core, never the service.
    const SERVICE: [&str; 3] = ["jobs", "http", "cli"];

    /// The `crate::NAME` paths of a file's non-test code (comments left out).
    fn uses(text: &str) -> Vec<String> {
        let code = text.split("#[cfg(test)]").next().unwrap_or("");
        let code: String = code.lines().filter(|l| !l.trim_start().starts_with("//")).flat_map(|l| [l, "\n"]).collect();
        code.split("crate::")
            .skip(1)
            .map(|s| s.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect())
            .collect()
    }

    fn files(dir: &std::path::Path, out: &mut Vec<std::path::PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                files(&p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }

    /// Issue 15: no module imports one above it (sim → flow → npe → discrepancy → plot →
    /// jobs → http → cli); the helpers beside the pipeline stay below the service.
    #[test]
    fn no_module_uses_one_above_it() {
        let src = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut all = Vec::new();
        files(&src, &mut all);
        let mut wrong = Vec::new();
        for f in &all {
            let rel = f.strip_prefix(&src).unwrap();
            let module = rel.iter().next().unwrap().to_string_lossy().trim_end_matches(".rs").to_string();
            if ["lib", "main"].contains(&module.as_str()) {
                continue;
            }
            let rank = PIPELINE.iter().position(|m| *m == module);
            for u in uses(&std::fs::read_to_string(f).unwrap()) {
                let above = match (rank, PIPELINE.iter().position(|m| *m == u)) {
                    (Some(r), Some(ru)) => ru > r,
                    (None, _) => SERVICE.contains(&u.as_str()),
                    _ => false,
                };
                if above {
                    wrong.push(format!("{} uses crate::{u}", rel.display()));
                }
            }
        }
        wrong.sort();
        wrong.dedup();
        assert!(wrong.is_empty(), "{wrong:#?}");
        assert!(uses("/// [`crate::jobs`]\nuse crate::http::X;\n#[cfg(test)]\nuse crate::cli;") == ["http"]);
    }
}
