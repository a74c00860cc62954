//! Device-side model state: weights uploaded once, and the activation workspace that plans and reuses
//! activation buffers while a forward pass is recorded.
use std::collections::HashMap;
use std::sync::Arc;

use anyhow::{anyhow, Result};

use super::weights::Weights;
use crate::ops::Recorder;
use crate::tensor::{DType, Tensor};
use crate::vk::{Buffer, BufferId, Context};

/// Weights of one component on the device, in one dtype.
pub struct DeviceWeights {
    pub(crate) ctx: Context,
    map: HashMap<String, Tensor>,
    pub dtype: DType,
    bytes: u64,
}

impl DeviceWeights {
    /// Uploads every tensor whose name starts with `prefix` (the prefix is stripped), converted to `dtype`.
    pub fn upload(ctx: &Context, w: &Weights, prefix: &str, dtype: DType) -> Result<Self> {
        let mut map = HashMap::new();
        let mut bytes = 0;
        for (name, t) in &w.tensors {
            if let Some(short) = name.strip_prefix(prefix) {
                let dt = Tensor::from_f32(ctx, &t.shape, dtype, &t.data, name)?;
                bytes += (t.data.len() * dtype.size()) as u64;
                map.insert(short.to_string(), dt);
            }
        }
        Ok(Self {
            ctx: ctx.clone(),
            map,
            dtype,
            bytes,
        })
    }

    pub fn get(&self, name: &str) -> Result<&Tensor> {
        self.map
            .get(name)
            .ok_or_else(|| anyhow!("weight {name:?} is missing"))
    }

    pub fn has(&self, name: &str) -> bool {
        self.map.contains_key(name)
    }

    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

/// Activation arena. `alloc` hands out a tensor on a free buffer large enough (smallest fit) or a new one;
/// `release` returns a buffer once the recorded ops no longer read it. Reuse inside one recording is safe
/// because the recorder inserts a barrier before a dispatch writes a buffer that earlier dispatches read.
///
/// Lifetimes are checked in debug builds: a released buffer is marked (`Buffer::set_released`) until `alloc`
/// hands it out again, and the recorder refuses a dispatch that uses it in between (an op recorded after the
/// release of a tensor it reads: the release came too early); releasing one buffer twice panics. A stale
/// tensor read after its buffer was handed out again *and written* by the new owner is not caught.
pub struct Workspace {
    ctx: Context,
    pub dtype: DType,
    free: Vec<Arc<Buffer>>,
    live: u64,
    peak: u64,
    total: u64,
    /// Group-norm statistics partials written together with an activation by its conv
    /// (`conv2d::stats_parts_shape`), keyed by the activation's buffer and shape; released with it.
    parts: Vec<(BufferId, Vec<usize>, Tensor)>,
}

impl Workspace {
    pub fn new(ctx: &Context, dtype: DType) -> Self {
        Self {
            ctx: ctx.clone(),
            dtype,
            free: vec![],
            live: 0,
            peak: 0,
            total: 0,
            parts: vec![],
        }
    }

    /// A tensor of the workspace dtype.
    pub fn alloc(&mut self, shape: &[usize]) -> Result<Tensor> {
        self.alloc_dtype(shape, self.dtype)
    }

    pub fn alloc_dtype(&mut self, shape: &[usize], dtype: DType) -> Result<Tensor> {
        let bytes = (shape.iter().product::<usize>() * dtype.size()) as u64;
        let fit = self
            .free
            .iter()
            .enumerate()
            .filter(|(_, b)| b.size() >= bytes && b.size() <= bytes.saturating_mul(4).max(4096))
            .min_by_key(|(_, b)| b.size())
            .map(|(i, _)| i);
        let buf = match fit {
            Some(i) => self.free.swap_remove(i),
            None => {
                let b = Arc::new(Buffer::new(&self.ctx, bytes.max(4), "activation")?);
                self.total += b.size();
                b
            }
        };
        buf.set_released(false);
        self.live += buf.size();
        self.peak = self.peak.max(self.live);
        // a reused buffer carries no partials of its earlier contents (release drops them; defensive)
        self.parts.retain(|(b, _, _)| *b != buf.id());
        Tensor::on_buffer(buf, shape, dtype)
    }

    /// Returns `t`'s buffer for reuse by later allocations (and the statistics partials attached to it).
    pub fn release(&mut self, t: Tensor) {
        let b = t.buffer().clone();
        debug_assert!(
            !b.is_released(),
            "workspace: buffer {:?} ({:?}) released twice",
            b.name(),
            b.id()
        );
        b.set_released(true);
        self.live = self.live.saturating_sub(b.size());
        let key = b.id();
        self.free.push(b);
        let (gone, keep): (Vec<_>, Vec<_>) = std::mem::take(&mut self.parts)
            .into_iter()
            .partition(|(k, _, _)| *k == key);
        self.parts = keep;
        for (_, _, p) in gone {
            self.release(p);
        }
    }

    /// Attaches statistics partials that the op writing `t` produced (see `conv2d::Conv2dArgs::stats_parts`).
    pub fn attach_parts(&mut self, t: &Tensor, parts: Tensor) {
        self.parts
            .push((t.buffer().id(), t.shape().to_vec(), parts));
    }

    /// The statistics partials written with `t`, if any.
    pub fn parts_of(&self, t: &Tensor) -> Option<&Tensor> {
        let key = t.buffer().id();
        self.parts
            .iter()
            .find(|(k, s, _)| *k == key && s.as_slice() == t.shape())
            .map(|(_, _, p)| p)
    }

    /// Bytes of activation buffers allocated (all of them stay allocated while the plan lives).
    pub fn allocated_bytes(&self) -> u64 {
        self.total
    }

    /// Peak bytes live at once.
    pub fn peak_live_bytes(&self) -> u64 {
        self.peak
    }
}

/// What a forward pass records into.
pub struct Fwd<'a> {
    pub rec: &'a mut Recorder,
    pub ws: &'a mut Workspace,
}
