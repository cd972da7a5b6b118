//! The simulator renders through the one chain (`field::InstrumentChain`, `docs/architecture.md`,
//! "The optical chain"): no file of `crates/sim/src` forms a Mueller product of its own.
//!
//! How it checks: the code of every file of `crates/sim/src` (comments, strings and the
//! `#[cfg(test)]` module left out) is split into tokens, and none may be the name of a Mueller
//! matrix or block type or of a method that evaluates or applies one (`Mueller`,
//! `LinearBlock`, `mueller_at`, `block_at`, `apply_at`, a plate's `matrix` or
//! `matrix_swept`, the analyser's `fluxes_at_plate`, `compile`, a telescope's `matrix_track`
//! or `telescope_matrix`): those live in `crates/field/src/chain.rs`,
//! `crates/field/src/render.rs` and `crates/field/src/analyser.rs`. The files that define an element of the chain (its own
//! block, as a field model) may name the element's matrix, not the chain's ones. And
//! `crates/sim/src/plan.rs` renders through the chain's forward model: it calls
//! `exposure_forward` and `fluxes`.

use crate::common;

use common::{code_only, tokens, workspace};

/// Names whose use outside the chain is a Mueller product or an element evaluated by hand.
const ELEMENT_NAMES: &[&str] = &["Mueller", "LinearBlock", "mueller_at", "block_at", "matrix"];

/// Names of the chain's own composition: the elements in turn, the plate, the analyser and
/// the telescope.
const CHAIN_NAMES: &[&str] = &[
    "apply_at",
    "matrix_swept",
    "fluxes_at_plate",
    "fluxes_at_plate_swept",
    "compile",
    "matrix_track",
    "telescope_matrix",
];

/// The files of `crates/sim/src` that define an element of the chain, with the element.
const ELEMENT_FILES: &[(&str, &str)] = &[
    ("crates/sim/src/stress.rs", "the stressed lens: its retardance block"),
    ("crates/sim/src/hwp_causes.rs", "the tilted and wedged plate: their equivalent block"),
];

/// The code tokens of `text` before its `#[cfg(test)]` module.
fn code_tokens_of(text: &str) -> Vec<common::Token> {
    let code = code_only(text);
    let end = code.find("#[cfg(test)]").unwrap_or(code.len());
    tokens(&code[..end])
}

/// The code tokens of the file `rel` before its `#[cfg(test)]` module.
fn code_tokens(rel: &str) -> Vec<common::Token> {
    code_tokens_of(&std::fs::read_to_string(workspace().join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}")))
}

/// The forbidden names in `toks` as `(line, name)`: the chain's own ones everywhere, an
/// element's ones outside an element's file.
fn forbidden(toks: &[common::Token], element: bool) -> Vec<(usize, String)> {
    toks.iter()
        .filter(|t| CHAIN_NAMES.contains(&t.text.as_str()) || (!element && ELEMENT_NAMES.contains(&t.text.as_str())))
        .map(|t| (t.line, t.text.clone()))
        .collect()
}

/// The check finds a product written by hand, and not a name in a comment, a string or a
/// longer identifier, nor in the tests module.
#[test]
fn the_check_finds_a_product_by_hand() {
    let code = "fn f(c: &Chain) {\n    let m = c.elements.mueller_at(x, y) * s;\n    // apply_at in a comment\n    \
                let t = \"matrix_swept in a string\";\n    let b = c.field_block_at(x, y);\n}\n\
                #[cfg(test)]\nmod tests { fn g() { h.matrix_swept(0.0, 0.1); } }\n";
    let found = forbidden(&code_tokens_of(code), false);
    assert_eq!(found, vec![(2, "mueller_at".to_string())]);
    assert!(forbidden(&code_tokens_of(code), true).is_empty(), "an element's file may name its own matrix");
}

#[test]
fn the_simulator_has_no_mueller_product_outside_the_chain() {
    let dir = workspace().join("crates/sim/src");
    let mut found = Vec::new();
    let mut files = 0;
    for p in common::files_under(&dir, Some(".rs")) {
        let rel = p.strip_prefix(workspace()).unwrap().to_string_lossy().replace('\\', "/");
        let element = ELEMENT_FILES.iter().any(|(f, _)| *f == rel);
        files += 1;
        for (line, name) in forbidden(&code_tokens(&rel), element) {
            found.push(format!("{rel}:{line}: `{name}`"));
        }
    }
    assert!(files >= 5, "crates/sim/src has {files} files: the test reads the wrong folder");
    assert!(
        found.is_empty(),
        "the simulator forms Mueller products outside the chain (field::InstrumentChain renders them):\n  {}",
        found.join("\n  ")
    );
    for (f, _) in ELEMENT_FILES {
        assert!(workspace().join(f).exists(), "{f} is listed as an element's file and is gone");
    }
}

#[test]
fn the_simulator_renders_through_the_chains_forward_model() {
    let toks = code_tokens("crates/sim/src/plan.rs");
    for name in ["exposure_forward", "fluxes", "before_exposures", "field_block_at"] {
        assert!(toks.iter().any(|t| t.text == name), "crates/sim/src/plan.rs no longer calls the chain's `{name}`");
    }
}
