//! The nuScenes v1.0 JSON tables (nutonomy/nuscenes-devkit docs/schema_nuscenes.md) with errors that name the
//! table, the row and the column: every file is a JSON array of objects keyed by a unique `token`; rows are
//! decoded column by column with serde, and foreign keys are resolved through a token index.
use crate::scene::import::bounds;
use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat3, DMat4, DQuat, DVec3};
use serde::de::DeserializeOwned;
use serde_json::Value;
use std::collections::HashMap;
use std::path::Path;

/// A loaded table: its rows (JSON objects) and their index by token.
pub struct Table {
    /// Table name as in the file name (`sample_data`) or `layer` of a map file.
    pub name: String,
    /// Where the table came from (for errors).
    pub file: String,
    pub rows: Vec<Value>,
    index: HashMap<String, usize>,
}

/// One row of a table; errors name `table`, row and token.
#[derive(Clone, Copy)]
pub struct Row<'a> {
    pub table: &'a Table,
    pub index: usize,
    obj: &'a serde_json::Map<String, Value>,
}

pub(crate) fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

impl Table {
    /// Reads `<dir>/<name>.json`.
    pub fn read(dir: &Path, name: &str) -> Result<Table> {
        let path = dir.join(format!("{name}.json"));
        let text = bounds::read_table_text(&path)
            .map_err(|why| anyhow!("nuScenes table `{name}`: {why}"))?;
        let v: Value = serde_json::from_str(&text).with_context(|| {
            format!(
                "nuScenes table `{name}` ({}): not valid JSON",
                path.display()
            )
        })?;
        Table::from_value(name, &path.display().to_string(), v)
    }

    /// A table from a JSON array of rows (`file` names the source in errors).
    pub fn from_value(name: &str, file: &str, v: Value) -> Result<Table> {
        let Value::Array(rows) = v else {
            bail!(
                "nuScenes table `{name}` ({file}): expected a JSON array of rows, found {}",
                kind(&v)
            );
        };
        let mut t = Table {
            name: name.to_string(),
            file: file.to_string(),
            rows,
            index: HashMap::new(),
        };
        let mut index = HashMap::with_capacity(t.rows.len());
        for i in 0..t.rows.len() {
            let r = t.row(i)?;
            let tok = r.str("token")?;
            if index.insert(tok.to_string(), i).is_some() {
                bail!("{}: duplicate token {tok:?}", r.at());
            }
        }
        t.index = index;
        Ok(t)
    }

    pub fn len(&self) -> usize {
        self.rows.len()
    }
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Row `i`; an error when it is not a JSON object.
    pub fn row(&self, i: usize) -> Result<Row<'_>> {
        match &self.rows[i] {
            Value::Object(obj) => Ok(Row {
                table: self,
                index: i,
                obj,
            }),
            other => bail!(
                "nuScenes table `{}` ({}) row {i}: expected an object, found {}",
                self.name,
                self.file,
                kind(other)
            ),
        }
    }

    /// Every row.
    pub fn iter(&self) -> impl Iterator<Item = Result<Row<'_>>> {
        (0..self.rows.len()).map(|i| self.row(i))
    }

    /// The row with `token`, if any.
    pub fn find(&self, token: &str) -> Option<Row<'_>> {
        self.index.get(token).and_then(|&i| self.row(i).ok())
    }
}

impl<'a> Row<'a> {
    /// "table `t` row i (token ...)" for errors.
    pub fn at(&self) -> String {
        match self.obj.get("token").and_then(Value::as_str) {
            Some(t) => format!(
                "nuScenes table `{}` ({}) row {} (token {t})",
                self.table.name, self.table.file, self.index
            ),
            None => format!(
                "nuScenes table `{}` ({}) row {}",
                self.table.name, self.table.file, self.index
            ),
        }
    }

    fn col(&self, col: &str) -> Result<&'a Value> {
        self.obj
            .get(col)
            .ok_or_else(|| anyhow!("{}: column `{col}` is missing", self.at()))
    }

    /// Column `col` decoded as `T`.
    pub fn get<T: DeserializeOwned>(&self, col: &str) -> Result<T> {
        T::deserialize(self.col(col)?).map_err(|e| anyhow!("{}: column `{col}`: {e}", self.at()))
    }

    /// A string column, borrowed.
    pub fn str(&self, col: &str) -> Result<&'a str> {
        let v = self.col(col)?;
        v.as_str().ok_or_else(|| {
            anyhow!(
                "{}: column `{col}`: expected a string, found {}",
                self.at(),
                kind(v)
            )
        })
    }

    /// A foreign key: the row of `target` whose token is in column `col`.
    pub fn follow<'t>(&self, col: &str, target: &'t Table) -> Result<Row<'t>> {
        let tok = self.str(col)?;
        target.find(tok).ok_or_else(|| {
            anyhow!(
                "{}: column `{col}`: no row of table `{}` has token {tok:?} (dangling token)",
                self.at(),
                target.name
            )
        })
    }

    /// A finite f64 array column of length N.
    pub fn vec<const N: usize>(&self, col: &str) -> Result<[f64; N]> {
        let v: Vec<f64> = self.get(col)?;
        if v.len() != N {
            bail!(
                "{}: column `{col}`: expected {N} numbers, found {}",
                self.at(),
                v.len()
            );
        }
        if v.iter().any(|x| !x.is_finite()) {
            bail!("{}: column `{col}`: non-finite value {v:?}", self.at());
        }
        Ok(std::array::from_fn(|i| v[i]))
    }

    /// A rotation quaternion column `[w, x, y, z]` (normalised; an error when its norm is far from 1).
    pub fn quat(&self, col: &str) -> Result<DQuat> {
        let [w, x, y, z] = self.vec::<4>(col)?;
        let q = DQuat::from_xyzw(x, y, z, w);
        let n = q.length();
        if !(0.9..=1.1).contains(&n) {
            bail!(
                "{}: column `{col}`: quaternion [w, x, y, z] = {:?} is not a rotation (norm {n})",
                self.at(),
                [w, x, y, z]
            );
        }
        Ok(q / n)
    }

    /// A 3-vector column whose entries are within `max` in absolute value (`what` names the bound in errors).
    pub fn vec3_within(&self, col: &str, max: f64, what: &str) -> Result<[f64; 3]> {
        let v = self.vec::<3>(col)?;
        if v.iter().any(|x| x.abs() > max) {
            bail!(
                "{}: column `{col}`: {v:?} lies beyond {max:e} m ({what})",
                self.at()
            );
        }
        Ok(v)
    }

    /// A global position column (`translation` of ego_pose / sample_annotation): within
    /// [`bounds::MAX_COORD_M`] of the map origin.
    pub fn position(&self, col: &str) -> Result<[f64; 3]> {
        self.vec3_within(col, bounds::MAX_COORD_M, "the largest coordinate accepted")
    }

    /// `translation` + `rotation` as a 4x4 `a2b` transform; the translation within `max_translation` m.
    pub fn transform(&self, max_translation: f64) -> Result<DMat4> {
        let t = self.vec3_within(
            "translation",
            max_translation,
            "the largest translation accepted",
        )?;
        Ok(DMat4::from_rotation_translation(
            self.quat("rotation")?,
            DVec3::from(t),
        ))
    }

    /// A 3x3 camera intrinsic column (rows), `None` when empty (sensors that are not cameras).
    pub fn intrinsic(&self, col: &str) -> Result<Option<DMat3>> {
        let rows: Vec<Vec<f64>> = self.get(col)?;
        if rows.is_empty() {
            return Ok(None);
        }
        if rows.len() != 3 || rows.iter().any(|r| r.len() != 3) {
            bail!(
                "{}: column `{col}`: expected a 3x3 matrix, found {rows:?}",
                self.at()
            );
        }
        if rows.iter().flatten().any(|x| !x.is_finite()) {
            bail!(
                "{}: column `{col}`: non-finite value in {rows:?}",
                self.at()
            );
        }
        let m = bounds::MAX_INTRINSIC_PX;
        if [rows[0][0], rows[0][1], rows[0][2], rows[1][1], rows[1][2]]
            .iter()
            .any(|x| x.abs() > m)
        {
            bail!(
                "{}: column `{col}`: {rows:?} has a focal length, skew or principal point beyond {m:e} px",
                self.at()
            );
        }
        if !(rows[0][0] > 0.0 && rows[1][1] > 0.0 && rows[2] == [0.0, 0.0, 1.0]) {
            bail!(
                "{}: column `{col}`: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, found {rows:?}",
                self.at()
            );
        }
        Ok(Some(DMat3::from_cols(
            DVec3::new(rows[0][0], rows[1][0], rows[2][0]),
            DVec3::new(rows[0][1], rows[1][1], rows[2][1]),
            DVec3::new(rows[0][2], rows[1][2], rows[2][2]),
        )))
    }
}

/// The tables the importer reads (`VERSION/<name>.json`).
pub const TABLES: [&str; 10] = [
    "scene",
    "log",
    "sample",
    "sample_data",
    "ego_pose",
    "calibrated_sensor",
    "sensor",
    "sample_annotation",
    "instance",
    "category",
];

/// The tables of one nuScenes version folder that the importer reads.
pub struct Tables {
    pub scene: Table,
    pub log: Table,
    pub sample: Table,
    pub sample_data: Table,
    pub ego_pose: Table,
    pub calibrated_sensor: Table,
    pub sensor: Table,
    pub sample_annotation: Table,
    pub instance: Table,
    pub category: Table,
}

impl Tables {
    /// Reads the tables of `<dataroot>/<version>/`.
    pub fn read(dir: &Path) -> Result<Tables> {
        if !dir.is_dir() {
            bail!(
                "nuScenes tables: {} is not a directory (expected DATAROOT/VERSION, e.g. data/nuscenes/v1.0-mini)",
                dir.display()
            );
        }
        Ok(Tables {
            scene: Table::read(dir, "scene")?,
            log: Table::read(dir, "log")?,
            sample: Table::read(dir, "sample")?,
            sample_data: Table::read(dir, "sample_data")?,
            ego_pose: Table::read(dir, "ego_pose")?,
            calibrated_sensor: Table::read(dir, "calibrated_sensor")?,
            sensor: Table::read(dir, "sensor")?,
            sample_annotation: Table::read(dir, "sample_annotation")?,
            instance: Table::read(dir, "instance")?,
            category: Table::read(dir, "category")?,
        })
    }
}
