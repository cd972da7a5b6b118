//! The one check of the numbers in the TOML files a user writes (instrument files, scenes,
//! standards lists): TOML can say `nan` and `inf`, which no key of these files means, and a
//! value that is not a finite number would otherwise travel far before anything fails (a bias
//! of NaN ADU simulates; a zero angle of infinity masks every pixel). Each loader calls
//! [`first_non_finite`] on the text before it deserializes, and refuses naming the file and the
//! key.

/// The first value in `text` (read as TOML) that is a float but not a finite number, as its
/// key path (`detector.bias_adu`, `filters[2].lambda_eff_nm`, `effects.instpol.coeffs_percent[1]`)
/// and its value; `None` when every number is finite or the text is not TOML (the
/// deserializer then says why).
pub fn first_non_finite(text: &str) -> Option<(String, f64)> {
    let table: toml::Table = text.parse().ok()?;
    walk_table(&table, "")
}

fn walk_table(t: &toml::Table, prefix: &str) -> Option<(String, f64)> {
    t.iter().find_map(|(k, v)| {
        let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
        walk(v, &key)
    })
}

fn walk(v: &toml::Value, key: &str) -> Option<(String, f64)> {
    match v {
        toml::Value::Float(x) if !x.is_finite() => Some((key.to_string(), *x)),
        toml::Value::Table(t) => walk_table(t, key),
        toml::Value::Array(a) => a.iter().enumerate().find_map(|(i, x)| walk(x, &format!("{key}[{i}]"))),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_nan_and_inf_anywhere_with_their_key() {
        assert_eq!(first_non_finite("a = 1.0\n[b]\nc = 2\n"), None);
        let (k, v) = first_non_finite("a = 1.0\n[b]\nc = nan\n").unwrap();
        assert_eq!(k, "b.c");
        assert!(v.is_nan());
        assert_eq!(first_non_finite("x = [1.0, -inf]\n"), Some(("x[1]".into(), f64::NEG_INFINITY)));
        assert_eq!(first_non_finite("[[f]]\nn = 1.0\n[[f]]\nn = +inf\n"), Some(("f[1].n".into(), f64::INFINITY)));
        assert_eq!(first_non_finite("not toml ["), None);
    }
}
