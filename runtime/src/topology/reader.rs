//! A spanned TOML table reader: typed getters that report wrong types, missing keys and
//! unknown keys as diagnostics with their line, so that a file's every problem is found in
//! one pass.

use std::collections::HashSet;
use std::ops::Range;

use toml::Spanned;
use toml::de::{DeTable, DeValue};

use super::{Diagnostic, SourceMap};

pub(super) type Value<'i> = Spanned<DeValue<'i>>;

pub(super) struct Walker {
    pub(super) map: SourceMap,
    pub(super) diags: Vec<Diagnostic>,
}

impl Walker {
    pub(super) fn err(&mut self, span: &Range<usize>, key: &str, message: impl Into<String>) {
        let d = self.map.diag(span, key, message);
        self.diags.push(d);
    }
}

/// A table being read: remembers which keys were used so the rest can be reported.
pub(super) struct Tbl<'t, 'i> {
    pub(super) table: &'t DeTable<'i>,
    pub(super) span: Range<usize>,
    pub(super) path: String,
    used: HashSet<&'t str>,
}

impl<'t, 'i> Tbl<'t, 'i> {
    pub(super) fn new(table: &'t DeTable<'i>, span: Range<usize>, path: String) -> Self {
        Tbl {
            table,
            span,
            path,
            used: HashSet::new(),
        }
    }

    pub(super) fn key(&self, k: &str) -> String {
        if self.path.is_empty() {
            k.to_string()
        } else {
            format!("{}.{k}", self.path)
        }
    }

    pub(super) fn get(&mut self, k: &'t str) -> Option<&'t Value<'i>> {
        self.used.insert(k);
        self.table.get(k)
    }

    pub(super) fn finish(&self, w: &mut Walker, allowed: &[&str]) {
        for (k, _) in self.table.iter() {
            if !self.used.contains(k.get_ref().as_ref()) {
                let key = self.key(k.get_ref());
                w.err(
                    &k.span(),
                    &key,
                    format!("unknown key (expected one of: {})", allowed.join(", ")),
                );
            }
        }
    }

    pub(super) fn missing(&self, w: &mut Walker, k: &str) {
        let key = self.key(k);
        w.err(&self.span, &key, "missing required key");
    }

    pub(super) fn string(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<String>> {
        let v = self.get(k)?;
        match v.get_ref() {
            DeValue::String(s) => Some(Spanned::new(v.span(), s.to_string())),
            other => {
                w.err(
                    &v.span(),
                    &self.key(k),
                    format!("expected a string, found {}", kind(other)),
                );
                None
            }
        }
    }

    pub(super) fn boolean(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<bool>> {
        let v = self.get(k)?;
        match v.get_ref() {
            DeValue::Boolean(b) => Some(Spanned::new(v.span(), *b)),
            other => {
                w.err(
                    &v.span(),
                    &self.key(k),
                    format!("expected true or false, found {}", kind(other)),
                );
                None
            }
        }
    }

    pub(super) fn req_string(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<String>> {
        if self.table.get(k).is_none() {
            self.missing(w, k);
        }
        self.string(w, k)
    }

    pub(super) fn float(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<f64>> {
        let v = self.get(k)?;
        let parsed = match v.get_ref() {
            DeValue::Float(f) => f.as_str().parse::<f64>().ok(),
            DeValue::Integer(i) => i64::from_str_radix(i.as_str(), i.radix())
                .ok()
                .map(|i| i as f64),
            other => {
                w.err(
                    &v.span(),
                    &self.key(k),
                    format!("expected a number, found {}", kind(other)),
                );
                return None;
            }
        };
        match parsed {
            Some(f) if f.is_finite() => Some(Spanned::new(v.span(), f)),
            _ => {
                w.err(&v.span(), &self.key(k), "expected a finite number");
                None
            }
        }
    }

    pub(super) fn uint(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<u64>> {
        let v = self.get(k)?;
        match v.get_ref() {
            DeValue::Integer(i) => match u64::from_str_radix(i.as_str(), i.radix()) {
                Ok(n) => Some(Spanned::new(v.span(), n)),
                Err(_) => {
                    w.err(
                        &v.span(),
                        &self.key(k),
                        format!("expected a non-negative integer, found {i}"),
                    );
                    None
                }
            },
            other => {
                w.err(
                    &v.span(),
                    &self.key(k),
                    format!("expected an integer, found {}", kind(other)),
                );
                None
            }
        }
    }

    pub(super) fn strings(&mut self, w: &mut Walker, k: &'t str) -> Option<Vec<Spanned<String>>> {
        let v = self.get(k)?;
        let DeValue::Array(items) = v.get_ref() else {
            w.err(
                &v.span(),
                &self.key(k),
                format!("expected an array of strings, found {}", kind(v.get_ref())),
            );
            return None;
        };
        let mut out = Vec::new();
        for (i, item) in items.iter().enumerate() {
            match item.get_ref() {
                DeValue::String(s) => out.push(Spanned::new(item.span(), s.to_string())),
                other => w.err(
                    &item.span(),
                    &format!("{}[{i}]", self.key(k)),
                    format!("expected a string, found {}", kind(other)),
                ),
            }
        }
        Some(out)
    }

    /// An array of tables (`[[k]]`), as (index, table) pairs.
    pub(super) fn tables(
        &mut self,
        w: &mut Walker,
        k: &'t str,
    ) -> Vec<(Tbl<'t, 'i>, Range<usize>)> {
        let Some(v) = self.get(k) else {
            return Vec::new();
        };
        let DeValue::Array(items) = v.get_ref() else {
            w.err(
                &v.span(),
                &self.key(k),
                format!(
                    "expected an array of tables (write `[[{k}]]`), found {}",
                    kind(v.get_ref())
                ),
            );
            return Vec::new();
        };
        let mut out = Vec::new();
        for (i, item) in items.iter().enumerate() {
            let path = format!("{}[{i}]", self.key(k));
            match item.get_ref() {
                DeValue::Table(t) => out.push((Tbl::new(t, item.span(), path), item.span())),
                other => w.err(
                    &item.span(),
                    &path,
                    format!("expected a table, found {}", kind(other)),
                ),
            }
        }
        out
    }

    pub(super) fn table(&mut self, w: &mut Walker, k: &'t str) -> Option<Tbl<'t, 'i>> {
        let v = self.get(k)?;
        match v.get_ref() {
            DeValue::Table(t) => Some(Tbl::new(t, v.span(), self.key(k))),
            other => {
                w.err(
                    &v.span(),
                    &self.key(k),
                    format!("expected a table, found {}", kind(other)),
                );
                None
            }
        }
    }
}

pub(super) fn kind(v: &DeValue<'_>) -> &'static str {
    match v {
        DeValue::String(_) => "a string",
        DeValue::Integer(_) => "an integer",
        DeValue::Float(_) => "a float",
        DeValue::Boolean(_) => "a boolean",
        DeValue::Datetime(_) => "a datetime",
        DeValue::Array(_) => "an array",
        DeValue::Table(_) => "a table",
    }
}

/// Converts a spanned TOML value into a plain `toml::Value` (for stage parameters).
pub(super) fn plain(v: &DeValue<'_>) -> Option<toml::Value> {
    Some(match v {
        DeValue::String(s) => toml::Value::String(s.to_string()),
        DeValue::Integer(i) => {
            toml::Value::Integer(i64::from_str_radix(i.as_str(), i.radix()).ok()?)
        }
        DeValue::Float(f) => toml::Value::Float(f.as_str().parse().ok()?),
        DeValue::Boolean(b) => toml::Value::Boolean(*b),
        DeValue::Datetime(d) => toml::Value::Datetime(*d),
        DeValue::Array(a) => toml::Value::Array(
            a.iter()
                .map(|x| plain(x.get_ref()))
                .collect::<Option<_>>()?,
        ),
        DeValue::Table(t) => toml::Value::Table(
            t.iter()
                .map(|(k, v)| Some((k.get_ref().to_string(), plain(v.get_ref())?)))
                .collect::<Option<_>>()?,
        ),
    })
}

/// Longest name: node names travel in the handshake, which carries at most 255 bytes.
pub(super) const MAX_NAME_BYTES: usize = 255;

pub(super) fn valid_name(s: &str) -> bool {
    !s.is_empty()
        && s.len() <= MAX_NAME_BYTES
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// A name cut to 40 characters for a message.
fn shorten(s: &str) -> String {
    if s.chars().count() <= 40 {
        s.to_string()
    } else {
        format!("{}…", s.chars().take(40).collect::<String>())
    }
}

pub(super) fn check_name(w: &mut Walker, name: &Spanned<String>, key: &str) {
    if !valid_name(name.get_ref()) {
        w.err(
            &name.span(),
            key,
            format!(
                "`{}` is not a valid name (1 to {MAX_NAME_BYTES} letters, digits, `_` and `-`)",
                shorten(name.get_ref())
            ),
        );
    }
}
