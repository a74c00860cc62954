//! Device tensors: a shape, a dtype and the buffer they own (shared through `Arc` so recordings can keep it
//! alive). Layout is always contiguous row-major; image tensors are (N, C, H, W).
use std::sync::Arc;

use anyhow::{ensure, Result};
use half::f16;

use crate::vk::{Buffer, Context};

/// Storage type of a tensor. Arithmetic is always f32 inside kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DType {
    F32,
    F16,
}

impl DType {
    pub fn size(self) -> usize {
        match self {
            DType::F32 => 4,
            DType::F16 => 2,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            DType::F32 => "f32",
            DType::F16 => "f16",
        }
    }
}

impl serde::Serialize for DType {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl std::str::FromStr for DType {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "f32" => Ok(DType::F32),
            "f16" => Ok(DType::F16),
            _ => anyhow::bail!("unknown dtype {s:?} (expected f32 or f16)"),
        }
    }
}

/// A device tensor.
#[derive(Clone)]
pub struct Tensor {
    shape: Vec<usize>,
    dtype: DType,
    buf: Arc<Buffer>,
}

impl std::fmt::Debug for Tensor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "Tensor({:?}, {}, {:?})",
            self.shape,
            self.dtype.name(),
            self.buf.name()
        )
    }
}

impl Tensor {
    /// An uninitialised tensor.
    pub fn empty(ctx: &Context, shape: &[usize], dtype: DType, name: &str) -> Result<Self> {
        ensure!(
            !shape.is_empty() && shape.iter().all(|&d| d > 0),
            "tensor {name:?}: empty shape {shape:?}"
        );
        let n: usize = shape.iter().product();
        ensure!(n < (1 << 31), "tensor {name:?}: {n} elements exceed 2^31");
        let buf = Buffer::new(ctx, (n * dtype.size()) as u64, name)?;
        Ok(Self {
            shape: shape.to_vec(),
            dtype,
            buf: Arc::new(buf),
        })
    }

    /// A tensor holding `data` (converted to `dtype`).
    pub fn from_f32(
        ctx: &Context,
        shape: &[usize],
        dtype: DType,
        data: &[f32],
        name: &str,
    ) -> Result<Self> {
        let n: usize = shape.iter().product();
        ensure!(
            data.len() == n,
            "tensor {name:?}: {} values for shape {shape:?} ({n} elements)",
            data.len()
        );
        let t = Self::empty(ctx, shape, dtype, name)?;
        t.write_f32(ctx, data)?;
        Ok(t)
    }

    /// A zero-filled tensor.
    pub fn zeros(ctx: &Context, shape: &[usize], dtype: DType, name: &str) -> Result<Self> {
        let n: usize = shape.iter().product();
        Self::from_f32(ctx, shape, dtype, &vec![0.0; n], name)
    }

    /// Overwrites the contents (the GPU must not be using the tensor).
    pub fn write_f32(&self, ctx: &Context, data: &[f32]) -> Result<()> {
        ensure!(
            data.len() == self.numel(),
            "tensor {:?}: {} values for {} elements",
            self.buf.name(),
            data.len(),
            self.numel()
        );
        match self.dtype {
            DType::F32 => self.buf.write(ctx, 0, bytemuck::cast_slice(data)),
            DType::F16 => {
                let h: Vec<f16> = data.iter().map(|&x| f16::from_f32(x)).collect();
                self.buf.write(ctx, 0, bytemuck::cast_slice(&h))
            }
        }
    }

    /// Downloads the contents as f32 (GPU work writing it must have completed).
    pub fn to_f32(&self, ctx: &Context) -> Result<Vec<f32>> {
        let bytes = self
            .buf
            .read(ctx, 0, (self.numel() * self.dtype.size()) as u64)?;
        Ok(match self.dtype {
            DType::F32 => bytes
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
            DType::F16 => bytes
                .chunks_exact(2)
                .map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect(),
        })
    }

    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    pub fn dtype(&self) -> DType {
        self.dtype
    }

    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn buffer(&self) -> &Arc<Buffer> {
        &self.buf
    }

    /// A tensor stored at the start of an existing buffer (at least as large as the tensor). Used by planners
    /// that reuse activation buffers across layers.
    pub fn on_buffer(buf: Arc<Buffer>, shape: &[usize], dtype: DType) -> Result<Self> {
        ensure!(
            !shape.is_empty() && shape.iter().all(|&d| d > 0),
            "tensor on {:?}: empty shape {shape:?}",
            buf.name()
        );
        let bytes = (shape.iter().product::<usize>() * dtype.size()) as u64;
        ensure!(
            bytes <= buf.size(),
            "tensor {shape:?} {} needs {bytes} bytes, buffer {:?} has {}",
            dtype.name(),
            buf.name(),
            buf.size()
        );
        Ok(Self {
            shape: shape.to_vec(),
            dtype,
            buf,
        })
    }

    /// The same storage viewed with another shape of equal element count.
    pub fn reshape(&self, shape: &[usize]) -> Result<Self> {
        let n: usize = shape.iter().product();
        ensure!(
            n == self.numel(),
            "reshape {:?} -> {shape:?}: element counts differ",
            self.shape
        );
        Ok(Self {
            shape: shape.to_vec(),
            dtype: self.dtype,
            buf: self.buf.clone(),
        })
    }
}
