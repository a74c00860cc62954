//! A safetensors shard being filled sample by sample: every tensor has a leading sample dimension `S`.
use anyhow::{ensure, Context, Result};
use safetensors::tensor::{Dtype, TensorView};
use std::collections::HashMap;
use std::path::Path;

struct Column {
    dtype: Dtype,
    /// Shape of one sample's item.
    item: Vec<usize>,
    data: Vec<u8>,
}

/// Tensors of one shard (little-endian bytes, as safetensors stores them).
#[derive(Default)]
pub struct Shard {
    columns: Vec<(String, Column)>,
    pub rows: usize,
}

/// Element types the shard writes.
pub trait Element: Copy {
    const DTYPE: Dtype;
    fn put(self, out: &mut Vec<u8>);
}

macro_rules! element {
    ($t:ty, $d:expr) => {
        impl Element for $t {
            const DTYPE: Dtype = $d;
            fn put(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
        }
    };
}
element!(u8, Dtype::U8);
element!(u16, Dtype::U16);
element!(i32, Dtype::I32);
element!(f32, Dtype::F32);
element!(f64, Dtype::F64);

impl Shard {
    /// Appends one sample's item of tensor `name` (shape `item`); the first row fixes dtype and shape.
    pub fn push<T: Element>(&mut self, name: &str, item: &[usize], values: &[T]) -> Result<()> {
        let n: usize = item.iter().product();
        ensure!(
            n == values.len(),
            "shard tensor {name}: {} values for item shape {item:?}",
            values.len()
        );
        let col = match self.columns.iter_mut().position(|(k, _)| k == name) {
            Some(i) => &mut self.columns[i].1,
            None => {
                self.columns.push((
                    name.to_string(),
                    Column {
                        dtype: T::DTYPE,
                        item: item.to_vec(),
                        data: Vec::new(),
                    },
                ));
                &mut self.columns.last_mut().expect("just pushed").1
            }
        };
        ensure!(
            col.dtype == T::DTYPE && col.item == item,
            "shard tensor {name}: item {item:?} {:?} differs from the first row's {:?} {:?}",
            T::DTYPE,
            col.item,
            col.dtype
        );
        col.data.reserve(n * T::DTYPE.size());
        for &v in values {
            v.put(&mut col.data);
        }
        Ok(())
    }

    /// Writes the shard (tensors `(S, *item)`) and empties it; checks every column has `rows` rows.
    pub fn write(&mut self, path: &Path, metadata: HashMap<String, String>) -> Result<()> {
        let mut views = Vec::new();
        for (name, c) in &self.columns {
            let per: usize = c.item.iter().product::<usize>() * c.dtype.size();
            ensure!(
                per * self.rows == c.data.len(),
                "shard tensor {name}: {} bytes for {} rows",
                c.data.len(),
                self.rows
            );
            let mut shape = vec![self.rows];
            shape.extend_from_slice(&c.item);
            views.push((name.clone(), TensorView::new(c.dtype, shape, &c.data)?));
        }
        safetensors::tensor::serialize_to_file(views, &Some(metadata), path)
            .with_context(|| format!("writing {}", path.display()))?;
        self.columns.clear();
        self.rows = 0;
        Ok(())
    }
}
