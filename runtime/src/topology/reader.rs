//! A spanned TOML table reader: typed getters that report wrong types, missing keys and
//! unknown keys as diagnostics with their line, so that a file's every problem is found in
//! one pass. Topology files are read with it, and so is any other file the project
//! validates the same way (an experiment file).

use std::collections::HashSet;
use std::ops::Range;

use toml::Spanned;
use toml::de::{DeTable, DeValue};

use super::{Diagnostic, SourceMap};

/// A TOML value with its byte span.
pub type Value<'i> = Spanned<DeValue<'i>>;

/// Walks one file: where its bytes are, and the problems found so far.
pub struct Walker {
    /// Byte offsets to lines.
    pub map: SourceMap,
    /// The problems found so far.
    pub diags: Vec<Diagnostic>,
}

impl Walker {
    /// A walker of `text`, read from `file` (for diagnostics).
    pub fn new(file: &str, text: &str) -> Walker {
        Walker {
            map: SourceMap::new(file, text),
            diags: Vec::new(),
        }
    }

    /// The root table of `text` (a TOML document; read it with
    /// `Tbl::new(root.get_ref(), root.span(), String::new())`), or `None` after reporting
    /// its syntax errors.
    pub fn document<'i>(&mut self, text: &'i str) -> Option<Spanned<DeTable<'i>>> {
        let (root, errors) = DeTable::parse_recoverable(text);
        if errors.is_empty() {
            return Some(root);
        }
        for e in errors {
            let span = e.span().unwrap_or(0..0);
            let msg = e.message().trim().to_string();
            self.err(&span, "<syntax>", format!("invalid TOML: {msg}"));
        }
        None
    }

    /// Every problem found, or `Ok` when there was none.
    pub fn finish(self) -> Result<(), super::TopologyErrors> {
        if self.diags.is_empty() {
            Ok(())
        } else {
            Err(super::TopologyErrors(self.diags))
        }
    }

    /// Reports a problem at byte span `span` of key `key`.
    pub fn err(&mut self, span: &Range<usize>, key: &str, message: impl Into<String>) {
        let d = self.map.diag(span, key, message);
        self.diags.push(d);
    }
}

/// A table being read: remembers which keys were used so the rest can be reported.
pub struct Tbl<'t, 'i> {
    /// The table.
    pub table: &'t DeTable<'i>,
    /// Its bytes in the file.
    pub span: Range<usize>,
    /// Its dotted key path (`""` for the root, `stage[1]`, ...).
    pub path: String,
    used: HashSet<&'t str>,
}

impl<'t, 'i> Tbl<'t, 'i> {
    /// Reads `table` (at `span`, named `path` in diagnostics).
    pub fn new(table: &'t DeTable<'i>, span: Range<usize>, path: String) -> Self {
        Tbl {
            table,
            span,
            path,
            used: HashSet::new(),
        }
    }

    /// The dotted path of key `k` of this table.
    pub fn key(&self, k: &str) -> String {
        if self.path.is_empty() {
            k.to_string()
        } else {
            format!("{}.{k}", self.path)
        }
    }

    /// Key `k`'s value, marking it used.
    pub fn get(&mut self, k: &'t str) -> Option<&'t Value<'i>> {
        self.used.insert(k);
        self.table.get(k)
    }

    /// Reports every key not read as unknown, listing the `allowed` ones.
    pub fn finish(&self, w: &mut Walker, allowed: &[&str]) {
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

    /// Reports that the required key `k` is missing.
    pub fn missing(&self, w: &mut Walker, k: &str) {
        let key = self.key(k);
        w.err(&self.span, &key, "missing required key");
    }

    /// Key `k` as a string (a problem if it is something else).
    pub fn string(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<String>> {
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

    /// Key `k` as a boolean.
    pub fn boolean(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<bool>> {
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

    /// Key `k` as a string, which must be there.
    pub fn req_string(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<String>> {
        if self.table.get(k).is_none() {
            self.missing(w, k);
        }
        self.string(w, k)
    }

    /// Key `k` as a finite number (an integer is taken too).
    pub fn float(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<f64>> {
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

    /// Key `k` as a non-negative integer.
    pub fn uint(&mut self, w: &mut Walker, k: &'t str) -> Option<Spanned<u64>> {
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

    /// Key `k` as an array of strings.
    pub fn strings(&mut self, w: &mut Walker, k: &'t str) -> Option<Vec<Spanned<String>>> {
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
    pub fn tables(&mut self, w: &mut Walker, k: &'t str) -> Vec<(Tbl<'t, 'i>, Range<usize>)> {
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

    /// Key `k` as a table.
    pub fn table(&mut self, w: &mut Walker, k: &'t str) -> Option<Tbl<'t, 'i>> {
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

/// What `v` is, for messages ("a string", "an array", ...).
pub fn kind(v: &DeValue<'_>) -> &'static str {
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
pub fn plain(v: &DeValue<'_>) -> Option<toml::Value> {
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
pub const MAX_NAME_BYTES: usize = 255;

/// Whether `s` is a valid name: 1 to 255 bytes of letters, digits, `_` and `-`.
pub fn valid_name(s: &str) -> bool {
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

/// Reports `name` (at `key`) unless it is a [`valid_name`].
pub fn check_name(w: &mut Walker, name: &Spanned<String>, key: &str) {
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
