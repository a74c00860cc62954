//! SQLite access for nuPlan log DBs and GeoPackage maps with errors that name the file, the table, the row (its
//! token or fid) and the column: tables and columns are checked before they are read, and every value is read
//! through a typed accessor.
use crate::scene::import::bounds;
use anyhow::{anyhow, bail, Context, Result};
use rusqlite::types::Value;
use rusqlite::{Connection, OpenFlags};
use std::collections::HashMap;
use std::path::Path;
use std::rc::Rc;

/// An open SQLite file (read only).
pub struct Db {
    pub conn: Connection,
    /// "nuPlan log DB <path>" / "nuPlan map <path>", for errors.
    pub what: String,
}

/// One row of a query: values by column name.
pub struct Rec {
    pub what: Rc<str>,
    pub table: Rc<str>,
    cols: Rc<HashMap<String, usize>>,
    vals: Vec<Value>,
}

/// Lower-case hex of a token BLOB (the devkit's `token.hex()`).
pub fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// Bytes of a hex token.
pub fn unhex(s: &str) -> Option<Vec<u8>> {
    if s.len() % 2 != 0 {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok())
        .collect()
}

fn kind(v: &Value) -> String {
    match v {
        Value::Null => "NULL".into(),
        Value::Integer(i) => format!("the integer {i}"),
        Value::Real(f) => format!("the real {f}"),
        Value::Text(t) => format!("the text {:?}", t.chars().take(40).collect::<String>()),
        Value::Blob(b) => format!("a blob of {} bytes", b.len()),
    }
}

impl Db {
    pub fn open(path: &Path, what: &str) -> Result<Db> {
        let what = format!("{what} {}", path.display());
        if !path.exists() {
            bail!("{what}: no such file");
        }
        // a FIFO, device or socket is refused before SQLite opens it
        crate::files::regular_file(path, "file").with_context(|| what.clone())?;
        let conn = Connection::open_with_flags(
            path,
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .with_context(|| format!("{what}: opening"))?;
        // A file that is not SQLite fails on its first read.
        conn.query_row("SELECT count(*) FROM sqlite_master", [], |r| {
            r.get::<_, i64>(0)
        })
        .map_err(|e| anyhow!("{what}: not a readable SQLite database ({e})"))?;
        Ok(Db { conn, what })
    }

    /// Whether `table` exists.
    pub fn has_table(&self, table: &str) -> Result<bool> {
        let n: i64 = self
            .conn
            .query_row(
                "SELECT count(*) FROM sqlite_master WHERE type IN ('table','view') AND name = ?1",
                [table],
                |r| r.get(0),
            )
            .with_context(|| format!("{}: reading sqlite_master", self.what))?;
        Ok(n > 0)
    }

    /// Checks that `table` exists with every column of `cols`.
    pub fn require(&self, table: &str, cols: &[&str]) -> Result<()> {
        if !self.has_table(table)? {
            bail!("{}: table `{table}` is missing", self.what);
        }
        let mut st = self
            .conn
            .prepare(&format!("PRAGMA table_info(\"{table}\")"))?;
        let have: Vec<String> = st
            .query_map([], |r| r.get::<_, String>(1))?
            .collect::<rusqlite::Result<_>>()?;
        for c in cols {
            if !have.iter().any(|h| h == c) {
                bail!(
                    "{}: table `{table}` has no column `{c}` (columns: {})",
                    self.what,
                    have.join(", ")
                );
            }
        }
        Ok(())
    }

    /// `SELECT cols FROM table tail` (the table and columns are checked first). The first column names the row
    /// in errors.
    pub fn select(
        &self,
        table: &str,
        cols: &[&str],
        tail: &str,
        params: &[&dyn rusqlite::ToSql],
    ) -> Result<Vec<Rec>> {
        self.require(table, cols)?;
        let list: Vec<String> = cols.iter().map(|c| format!("\"{c}\"")).collect();
        let sql = format!("SELECT {} FROM \"{table}\" {tail}", list.join(", "));
        let mut st = self
            .conn
            .prepare(&sql)
            .with_context(|| format!("{}: table `{table}`: preparing {sql}", self.what))?;
        let index: Rc<HashMap<String, usize>> = Rc::new(
            cols.iter()
                .enumerate()
                .map(|(i, c)| (c.to_string(), i))
                .collect(),
        );
        let (what, tname): (Rc<str>, Rc<str>) = (self.what.as_str().into(), table.into());
        let rows = st
            .query_map(params, |r| {
                (0..cols.len())
                    .map(|i| r.get::<_, Value>(i))
                    .collect::<rusqlite::Result<Vec<Value>>>()
            })
            .with_context(|| format!("{}: table `{table}`: reading", self.what))?;
        let mut out = Vec::new();
        for r in rows {
            out.push(Rec {
                what: what.clone(),
                table: tname.clone(),
                cols: index.clone(),
                vals: r.with_context(|| format!("{}: table `{table}`: reading", self.what))?,
            });
        }
        Ok(out)
    }
}

impl Rec {
    /// "<file>: table `t` row <token|fid>" for errors.
    pub fn at(&self) -> String {
        let id = match self.vals.first() {
            Some(Value::Blob(b)) => format!("token {}", hex(b)),
            Some(Value::Integer(i)) => format!("{} {i}", self.cols_name(0)),
            Some(v) => format!("with {} {}", self.cols_name(0), kind(v)),
            None => "?".into(),
        };
        format!("{}: table `{}` row {id}", self.what, self.table)
    }
    fn cols_name(&self, i: usize) -> String {
        self.cols
            .iter()
            .find(|(_, &j)| j == i)
            .map(|(c, _)| c.clone())
            .unwrap_or_default()
    }
    fn raw(&self, col: &str) -> &Value {
        &self.vals[*self
            .cols
            .get(col)
            .unwrap_or_else(|| panic!("column {col} was not selected"))]
    }
    fn bad(&self, col: &str, want: &str) -> anyhow::Error {
        anyhow!(
            "{}: column `{col}`: expected {want}, found {}",
            self.at(),
            kind(self.raw(col))
        )
    }
    pub fn is_null(&self, col: &str) -> bool {
        matches!(self.raw(col), Value::Null)
    }
    pub fn f64(&self, col: &str) -> Result<f64> {
        match self.raw(col) {
            Value::Real(f) if f.is_finite() => Ok(*f),
            Value::Integer(i) => Ok(*i as f64),
            _ => Err(self.bad(col, "a finite number")),
        }
    }
    /// A finite number within `max` in absolute value (`unit` names what it measures, for the error).
    pub fn f64_within(&self, col: &str, max: f64, unit: &str) -> Result<f64> {
        let v = self.f64(col)?;
        if v.abs() > max {
            bail!(
                "{}: column `{col}`: {v} {unit} is beyond {max:e} {unit}, the largest accepted",
                self.at()
            );
        }
        Ok(v)
    }
    /// A coordinate (m) within [`bounds::MAX_COORD_M`] of the map origin.
    pub fn coord(&self, col: &str) -> Result<f64> {
        self.f64_within(col, bounds::MAX_COORD_M, "m")
    }
    /// A velocity component (m/s) within [`bounds::MAX_SPEED_MPS`].
    pub fn speed(&self, col: &str) -> Result<f64> {
        self.f64_within(col, bounds::MAX_SPEED_MPS, "m/s")
    }
    /// A timestamp (us) within [`bounds::MAX_TIMESTAMP_US`] of 0 (so that differences cannot overflow).
    pub fn timestamp(&self, col: &str) -> Result<i64> {
        let t = self.i64(col)?;
        if !(-bounds::MAX_TIMESTAMP_US..=bounds::MAX_TIMESTAMP_US).contains(&t) {
            bail!(
                "{}: column `{col}`: {t} us is beyond {} us",
                self.at(),
                bounds::MAX_TIMESTAMP_US
            );
        }
        Ok(t)
    }
    /// Text that may name a file or folder as is ([`bounds::plain_name`]).
    pub fn plain_text(&self, col: &str) -> Result<&str> {
        let t = self.text(col)?;
        bounds::plain_name(t).map_err(|why| anyhow!("{}: column `{col}`: {why}", self.at()))?;
        Ok(t)
    }
    pub fn opt_f64(&self, col: &str) -> Result<Option<f64>> {
        if self.is_null(col) {
            Ok(None)
        } else {
            self.f64(col).map(Some)
        }
    }
    pub fn i64(&self, col: &str) -> Result<i64> {
        match self.raw(col) {
            Value::Integer(i) => Ok(*i),
            _ => Err(self.bad(col, "an integer")),
        }
    }
    pub fn opt_i64(&self, col: &str) -> Result<Option<i64>> {
        if self.is_null(col) {
            Ok(None)
        } else {
            self.i64(col).map(Some)
        }
    }
    pub fn text(&self, col: &str) -> Result<&str> {
        match self.raw(col) {
            Value::Text(t) => Ok(t),
            _ => Err(self.bad(col, "text")),
        }
    }
    pub fn opt_text(&self, col: &str) -> Result<Option<&str>> {
        if self.is_null(col) {
            Ok(None)
        } else {
            self.text(col).map(Some)
        }
    }
    pub fn blob(&self, col: &str) -> Result<&[u8]> {
        match self.raw(col) {
            Value::Blob(b) => Ok(b),
            _ => Err(self.bad(col, "a blob")),
        }
    }
    /// A token (BLOB) as hex.
    pub fn token(&self, col: &str) -> Result<String> {
        match self.raw(col) {
            Value::Blob(b) if !b.is_empty() => Ok(hex(b)),
            _ => Err(self.bad(col, "a token (a non-empty blob)")),
        }
    }
    /// A token that may be NULL.
    pub fn opt_token(&self, col: &str) -> Result<Option<String>> {
        if self.is_null(col) {
            Ok(None)
        } else {
            self.token(col).map(Some)
        }
    }
    /// An id column (a fid): an integer, an integral real or non-empty text; None when NULL or empty text.
    pub fn opt_id(&self, col: &str) -> Result<Option<String>> {
        match self.raw(col) {
            Value::Null => Ok(None),
            Value::Integer(i) => Ok(Some(i.to_string())),
            Value::Real(f) if f.fract() == 0.0 && f.abs() < 9e15 => {
                Ok(Some((*f as i64).to_string()))
            }
            Value::Text(t) if t.trim().is_empty() => Ok(None),
            Value::Text(t) => Ok(Some(t.trim().to_string())),
            _ => Err(self.bad(col, "an id (integer or text)")),
        }
    }
    /// A pickled numeric array of `n` values.
    pub fn pickled(&self, col: &str, n: usize) -> Result<Vec<f64>> {
        let b = self.blob(col)?;
        super::pickle::floats(b, n)
            .map_err(|e| anyhow!("{}: column `{col}`: pickled array: {e}", self.at()))
    }
    /// A GeoPackage geometry.
    pub fn geometry(&self, col: &str) -> Result<super::wkb::Geometry> {
        let b = self.blob(col)?;
        super::wkb::parse_gpkg(b).map_err(|e| anyhow!("{}: column `{col}`: {e}", self.at()))
    }
}
