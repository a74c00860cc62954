//! Command recording: many dispatches in one command buffer, with barriers inserted only where a dispatch
//! touches a buffer that an earlier dispatch since the last barrier wrote (RAW/WAW) or read (WAR).
//! A finished [`Recording`] can be submitted many times (record once, replay per sampling step).
use std::collections::HashSet;
use std::sync::Arc;

use anyhow::{ensure, Result};
use ash::vk;

use super::memory::Buffer;
use super::{vk_err, Context};
use crate::kernels::KernelId;

const SETS_PER_POOL: u32 = 512;
const MAX_BINDINGS: u32 = 8;
// texel-view bindings a dispatch may average (a pool holds SETS_PER_POOL * this; see `descriptor_set`)
const MAX_IMAGE_BINDINGS: u32 = 2;

/// GPU time of one labelled dispatch (from timestamp queries).
#[derive(Clone, Debug)]
pub struct Timing {
    pub label: String,
    pub ms: f64,
}

/// Records dispatches into one command buffer.
pub struct Recorder {
    ctx: Context,
    // Each recorder owns its command pool: a pool must be externally synchronised while any of its command
    // buffers records, so per-recorder pools let threads record concurrently.
    cmd_pool: vk::CommandPool,
    cmd: vk::CommandBuffer,
    pools: Vec<vk::DescriptorPool>,
    sets_left: u32,
    keep: Vec<Arc<Buffer>>,
    written: HashSet<vk::Buffer>,
    read: HashSet<vk::Buffer>,
    queries: Option<(vk::QueryPool, u32)>,
    labels: Vec<String>,
    dispatches: usize,
    // op-internal temporaries shared by all ops of this recording (see `scratch`)
    scratch: Vec<Option<Arc<Buffer>>>,
}

/// A finished command buffer, ready to submit (repeatedly).
pub struct Recording {
    ctx: Context,
    cmd_pool: vk::CommandPool,
    cmd: vk::CommandBuffer,
    pools: Vec<vk::DescriptorPool>,
    _keep: Vec<Arc<Buffer>>,
    fence: vk::Fence,
    queries: Option<(vk::QueryPool, u32)>,
    labels: Vec<String>,
    dispatches: usize,
}

impl Context {
    /// Starts a recording.
    pub fn recorder(&self) -> Result<Recorder> {
        Recorder::new(self, if self.inner.profile { 16384 } else { 0 })
    }

    /// Starts a recording that writes a GPU timestamp after each of up to `max` dispatches.
    pub fn recorder_timed(&self, max: u32) -> Result<Recorder> {
        Recorder::new(self, max)
    }
}

impl Recorder {
    fn new(ctx: &Context, timestamps: u32) -> Result<Self> {
        let d = &ctx.inner.device;
        let pci = vk::CommandPoolCreateInfo::default().queue_family_index(ctx.inner.queue_family);
        // SAFETY: valid device; the pool is owned by this recorder (then its recording) alone.
        let cmd_pool =
            unsafe { d.create_command_pool(&pci, None) }.map_err(vk_err("vkCreateCommandPool"))?;
        let ai = vk::CommandBufferAllocateInfo::default()
            .command_pool(cmd_pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool is fresh and used by this thread only.
        let cmd = match unsafe { d.allocate_command_buffers(&ai) } {
            Ok(c) => c[0],
            Err(e) => {
                // SAFETY: nothing was allocated from the pool.
                unsafe { d.destroy_command_pool(cmd_pool, None) };
                return Err(vk_err("vkAllocateCommandBuffers")(e));
            }
        };
        // SAFETY: fresh command buffer.
        unsafe { d.begin_command_buffer(cmd, &vk::CommandBufferBeginInfo::default()) }
            .map_err(vk_err("vkBeginCommandBuffer"))?;
        let mut r = Self {
            ctx: ctx.clone(),
            cmd_pool,
            cmd,
            pools: vec![],
            sets_left: 0,
            keep: vec![],
            written: HashSet::new(),
            read: HashSet::new(),
            queries: None,
            labels: vec![],
            dispatches: 0,
            scratch: vec![],
        };
        if timestamps > 0 && ctx.inner.info.timestamps {
            let n = timestamps + 1;
            let qi = vk::QueryPoolCreateInfo::default()
                .query_type(vk::QueryType::TIMESTAMP)
                .query_count(n);
            // SAFETY: valid device; the pool is reset inside the command buffer before use.
            unsafe {
                let qp = d
                    .create_query_pool(&qi, None)
                    .map_err(vk_err("vkCreateQueryPool"))?;
                d.cmd_reset_query_pool(cmd, qp, 0, n);
                d.cmd_write_timestamp(cmd, vk::PipelineStageFlags::TOP_OF_PIPE, qp, 0);
                r.queries = Some((qp, n));
            }
        }
        Ok(r)
    }

    fn barrier_if_needed(&mut self, reads: &[vk::Buffer], writes: &[vk::Buffer]) {
        let hazard = reads.iter().chain(writes).any(|b| self.written.contains(b))
            || writes.iter().any(|b| self.read.contains(b));
        if hazard {
            let mb = [vk::MemoryBarrier::default()
                .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
                .dst_access_mask(
                    vk::AccessFlags::SHADER_READ
                        | vk::AccessFlags::SHADER_WRITE
                        | vk::AccessFlags::TRANSFER_READ
                        | vk::AccessFlags::TRANSFER_WRITE,
                )];
            let stages = vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER;
            // SAFETY: recording state; a global memory barrier has no resource references.
            unsafe {
                self.ctx.inner.device.cmd_pipeline_barrier(
                    self.cmd,
                    stages,
                    stages,
                    vk::DependencyFlags::empty(),
                    &mb,
                    &[],
                    &[],
                )
            };
            self.written.clear();
            self.read.clear();
        }
        self.read.extend(reads);
        self.written.extend(writes);
    }

    fn descriptor_set(&mut self, layout: vk::DescriptorSetLayout) -> Result<vk::DescriptorSet> {
        let d = &self.ctx.inner.device;
        if self.sets_left == 0 {
            let sizes = [
                vk::DescriptorPoolSize::default()
                    .ty(vk::DescriptorType::STORAGE_BUFFER)
                    .descriptor_count(SETS_PER_POOL * MAX_BINDINGS),
                vk::DescriptorPoolSize::default()
                    .ty(vk::DescriptorType::STORAGE_IMAGE)
                    .descriptor_count(SETS_PER_POOL * MAX_IMAGE_BINDINGS),
            ];
            let pci = vk::DescriptorPoolCreateInfo::default()
                .max_sets(SETS_PER_POOL)
                .pool_sizes(&sizes);
            // SAFETY: valid device.
            let pool = unsafe { d.create_descriptor_pool(&pci, None) }
                .map_err(vk_err("vkCreateDescriptorPool"))?;
            self.pools.push(pool);
            self.sets_left = SETS_PER_POOL;
        }
        self.sets_left -= 1;
        let layouts = [layout];
        let ai = vk::DescriptorSetAllocateInfo::default()
            .descriptor_pool(*self.pools.last().expect("pool"))
            .set_layouts(&layouts);
        // SAFETY: the pool has room (counted above) and is used by this recorder only.
        Ok(unsafe { d.allocate_descriptor_sets(&ai) }
            .map_err(vk_err("vkAllocateDescriptorSets"))?[0])
    }

    /// Records one dispatch of `kernel` with `buffers` bound to bindings 0..n, push constants `params` and
    /// `groups` work groups. `label` names it in timings.
    pub fn dispatch(
        &mut self,
        kernel: KernelId,
        buffers: &[&Arc<Buffer>],
        params: &[u8],
        groups: [u32; 3],
        label: &str,
    ) -> Result<()> {
        let p = self.ctx.pipeline(kernel)?;
        let info = p.info;
        ensure!(
            buffers.len() == info.bindings.len(),
            "kernel {}: {} buffers bound, the kernel has {} bindings",
            info.name,
            buffers.len(),
            info.bindings.len()
        );
        ensure!(
            params.len() as u32 == info.params_size,
            "kernel {}: {} parameter bytes, the kernel expects {}",
            info.name,
            params.len(),
            info.params_size
        );
        ensure!(
            groups.iter().all(|&g| g >= 1),
            "kernel {}: empty grid {groups:?}",
            info.name
        );
        ensure!(
            groups.iter().all(|&g| g <= 65535),
            "kernel {}: grid {groups:?} exceeds 65535 per dimension",
            info.name
        );
        #[cfg(debug_assertions)]
        for (i, b) in buffers.iter().enumerate() {
            ensure!(
                !b.is_released(),
                "{label}: kernel {} uses buffer {:?} ({:?}, binding {i}) after its pool released it (a release \
                 recorded before this last use)",
                info.name,
                b.name(),
                b.id()
            );
        }
        let mut reads = vec![];
        let mut writes = vec![];
        for (b, ro) in buffers.iter().zip(info.bindings) {
            if *ro {
                reads.push(b.raw)
            } else {
                writes.push(b.raw)
            }
        }
        self.barrier_if_needed(&reads, &writes);
        ensure!(
            info.images.iter().filter(|&&i| i).count() as u32 <= MAX_IMAGE_BINDINGS,
            "kernel {}: more than {MAX_IMAGE_BINDINGS} texel-view bindings",
            info.name
        );
        let set = self.descriptor_set(p.set_layout)?;
        let infos: Vec<[vk::DescriptorBufferInfo; 1]> = buffers
            .iter()
            .map(|b| {
                [vk::DescriptorBufferInfo::default()
                    .buffer(b.raw)
                    .offset(0)
                    .range(vk::WHOLE_SIZE)]
            })
            .collect();
        let mut image_infos: Vec<[vk::DescriptorImageInfo; 1]> = vec![];
        for (b, &img) in buffers.iter().zip(info.images) {
            let view = if img {
                b.texel_view()?
            } else {
                vk::ImageView::null()
            };
            image_infos.push([vk::DescriptorImageInfo::default()
                .image_view(view)
                .image_layout(vk::ImageLayout::GENERAL)]);
        }
        let writes_ds: Vec<_> = infos
            .iter()
            .zip(&image_infos)
            .enumerate()
            .map(|(i, (bi, ii))| {
                let w = vk::WriteDescriptorSet::default()
                    .dst_set(set)
                    .dst_binding(i as u32)
                    .descriptor_type(super::pipeline::descriptor_type(info, i));
                if info.images[i] {
                    w.image_info(ii)
                } else {
                    w.buffer_info(bi)
                }
            })
            .collect();
        let d = &self.ctx.inner.device;
        // SAFETY: all handles are alive (buffers kept in `keep`, pipeline in the context cache) and the command
        // buffer is in the recording state.
        unsafe {
            d.update_descriptor_sets(&writes_ds, &[]);
            d.cmd_bind_pipeline(self.cmd, vk::PipelineBindPoint::COMPUTE, p.pipeline);
            d.cmd_bind_descriptor_sets(
                self.cmd,
                vk::PipelineBindPoint::COMPUTE,
                p.layout,
                0,
                &[set],
                &[],
            );
            if !params.is_empty() {
                d.cmd_push_constants(self.cmd, p.layout, vk::ShaderStageFlags::COMPUTE, 0, params);
            }
            d.cmd_dispatch(self.cmd, groups[0], groups[1], groups[2]);
        }
        self.keep.extend(buffers.iter().map(|b| (*b).clone()));
        self.dispatches += 1;
        if let Some((qp, n)) = self.queries {
            let q = self.labels.len() as u32 + 1;
            if q < n {
                // SAFETY: query index within the pool, reset at the start of this command buffer.
                unsafe {
                    d.cmd_write_timestamp(self.cmd, vk::PipelineStageFlags::COMPUTE_SHADER, qp, q)
                };
                self.labels.push(label.to_string());
            }
        }
        Ok(())
    }

    /// Records a buffer copy. Both buffers must stay alive until the recording has completed.
    pub(crate) fn copy(
        &mut self,
        src: &Buffer,
        src_off: u64,
        dst: &Buffer,
        dst_off: u64,
        len: u64,
    ) {
        self.barrier_if_needed(&[src.raw], &[dst.raw]);
        let r = [vk::BufferCopy::default()
            .src_offset(src_off)
            .dst_offset(dst_off)
            .size(len)];
        // SAFETY: recording state, valid buffers (caller keeps them alive), ranges checked by the callers.
        unsafe {
            self.ctx
                .inner
                .device
                .cmd_copy_buffer(self.cmd, src.raw, dst.raw, &r)
        };
    }

    /// Records a copy between two kept-alive buffers.
    pub fn copy_buffer(&mut self, src: &Arc<Buffer>, dst: &Arc<Buffer>, len: u64) -> Result<()> {
        ensure!(
            len <= src.size() && len <= dst.size(),
            "copy of {len} bytes exceeds a buffer"
        );
        #[cfg(debug_assertions)]
        for b in [src, dst] {
            ensure!(
                !b.is_released(),
                "copy of {len} bytes uses buffer {:?} ({:?}) after its pool released it",
                b.name(),
                b.id()
            );
        }
        self.copy(src, 0, dst, 0, len);
        self.keep.push(src.clone());
        self.keep.push(dst.clone());
        Ok(())
    }

    /// A temporary buffer of at least `bytes` for op-internal use, shared by every op of this recording that
    /// asks for the same `slot`: dispatches run in recording order and the hazard tracking inserts barriers
    /// between users, so one buffer per slot serves them all. A larger request allocates a new buffer (the
    /// dispatches recorded on the old one keep it alive).
    pub fn scratch(&mut self, slot: usize, bytes: u64) -> Result<Arc<Buffer>> {
        if self.scratch.len() <= slot {
            self.scratch.resize(slot + 1, None);
        }
        if let Some(b) = &self.scratch[slot] {
            if b.size() >= bytes {
                return Ok(b.clone());
            }
        }
        let b = Arc::new(Buffer::new(&self.ctx, bytes, &format!("scratch-{slot}"))?);
        self.scratch[slot] = Some(b.clone());
        Ok(b)
    }

    /// Number of dispatches recorded so far.
    pub fn dispatch_count(&self) -> usize {
        self.dispatches
    }

    /// The context this recorder records for (launchers ask it which kernels the device supports).
    pub fn context(&self) -> &Context {
        &self.ctx
    }

    /// Ends recording.
    pub fn finish(mut self) -> Result<Recording> {
        let d = &self.ctx.inner.device;
        // SAFETY: recording state; the fence is fresh.
        let fence = unsafe {
            d.end_command_buffer(self.cmd)
                .map_err(vk_err("vkEndCommandBuffer"))?;
            d.create_fence(&vk::FenceCreateInfo::default(), None)
                .map_err(vk_err("vkCreateFence"))?
        };
        let rec = Recording {
            ctx: self.ctx.clone(),
            cmd_pool: self.cmd_pool,
            cmd: self.cmd,
            pools: std::mem::take(&mut self.pools),
            _keep: std::mem::take(&mut self.keep),
            fence,
            queries: self.queries.take(),
            labels: std::mem::take(&mut self.labels),
            dispatches: self.dispatches,
        };
        // Ownership of the command buffer moved to the Recording: Drop below must not free it.
        self.cmd = vk::CommandBuffer::null();
        self.cmd_pool = vk::CommandPool::null();
        Ok(rec)
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        // An abandoned recorder (an op failed mid-recording): free what it allocated; nothing was submitted.
        let d = &self.ctx.inner.device;
        // SAFETY: the command buffer was never submitted; destroying the pool frees it.
        unsafe {
            if self.cmd_pool != vk::CommandPool::null() {
                d.destroy_command_pool(self.cmd_pool, None);
            }
            for p in self.pools.drain(..) {
                d.destroy_descriptor_pool(p, None);
            }
            if let Some((qp, _)) = self.queries.take() {
                d.destroy_query_pool(qp, None);
            }
        }
    }
}

impl Recording {
    /// Submits and waits for completion.
    pub fn submit_wait(&self) -> Result<()> {
        let d = &self.ctx.inner.device;
        let cmds = [self.cmd];
        let si = [vk::SubmitInfo::default().command_buffers(&cmds)];
        {
            let q = self.ctx.inner.queue.lock().expect("queue lock");
            // SAFETY: the queue mutex serialises submits; the fence is unsignalled.
            unsafe { d.queue_submit(*q, &si, self.fence) }.map_err(vk_err("vkQueueSubmit"))?;
        }
        // SAFETY: fence of this device.
        unsafe {
            d.wait_for_fences(&[self.fence], true, u64::MAX)
                .map_err(vk_err("vkWaitForFences"))?;
            d.reset_fences(&[self.fence])
                .map_err(vk_err("vkResetFences"))?;
        }
        Ok(())
    }

    /// Number of dispatches in the recording.
    pub fn dispatch_count(&self) -> usize {
        self.dispatches
    }

    /// Per-dispatch GPU times of the last submit (empty without timestamps).
    pub fn timings(&self) -> Result<Vec<Timing>> {
        let Some((qp, _)) = self.queries else {
            return Ok(vec![]);
        };
        let n = self.labels.len() + 1;
        let mut data = vec![0u64; n];
        // SAFETY: the last submit completed (submit_wait), so the queries are available.
        unsafe {
            self.ctx.inner.device.get_query_pool_results(
                qp,
                0,
                &mut data,
                vk::QueryResultFlags::TYPE_64,
            )
        }
        .map_err(vk_err("vkGetQueryPoolResults"))?;
        let period = self.ctx.inner.info.timestamp_period_ns as f64;
        Ok(self
            .labels
            .iter()
            .enumerate()
            .map(|(i, l)| Timing {
                label: l.clone(),
                ms: (data[i + 1].wrapping_sub(data[i])) as f64 * period * 1e-6,
            })
            .collect())
    }
}

impl Drop for Recording {
    fn drop(&mut self) {
        let d = &self.ctx.inner.device;
        // SAFETY: every submit waited on the fence, so the command buffer is not pending.
        unsafe {
            d.destroy_command_pool(self.cmd_pool, None);
            d.destroy_fence(self.fence, None);
            for p in self.pools.drain(..) {
                d.destroy_descriptor_pool(p, None);
            }
            if let Some((qp, _)) = self.queries.take() {
                d.destroy_query_pool(qp, None);
            }
        }
    }
}
