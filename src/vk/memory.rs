//! Device buffers: a buffer owns its gpu-allocator allocation; upload/download go through the mapping when the
//! memory is host-visible and coherent (lavapipe, integrated GPUs), else through a staging buffer.
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use anyhow::{ensure, Context as _, Result};
use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use super::image::{TexelView, IMAGE_ROW_BYTES};
use super::{vk_err, Context, Inner};

/// Smallest buffer given a texel view: down to a 64 x 16 f32 weight. Smaller ones would pay up to 16x in
/// padding (lavapipe pads a linear image to 4 rows of 16 KiB); b2dr-tiny's whole sampling pipeline takes 703
/// MiB without texel views, 718 with them from 16 KiB, 724 from 4 KiB (the step's small linears gain).
pub const TEXEL_MIN_BYTES: u64 = 4096;

/// A buffer's identity, unique for the life of the process (unlike a raw pointer or a Vulkan handle, never
/// reused after the buffer is dropped): what pools key their bookkeeping by.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BufferId(u64);

/// A storage buffer with its memory.
pub struct Buffer {
    pub(crate) ctx: Arc<Inner>,
    pub(crate) raw: vk::Buffer,
    id: BufferId,
    // set by a pool (the activation workspace) while the buffer sits on its free list: debug builds refuse to
    // record a dispatch or copy that uses it then (`Recorder::dispatch`)
    released: AtomicBool,
    alloc: Option<Allocation>,
    size: u64,
    name: String,
    // allocated with room for a texel view (whole image rows plus the image's padding)
    texel_sized: bool,
    // the storage-image view of this buffer's bytes, created at first use (see `vk::image`)
    texels: Mutex<Option<TexelView>>,
}

impl std::fmt::Debug for Buffer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Buffer({:?}, {} bytes)", self.name, self.size)
    }
}

impl Buffer {
    /// Creates a device-local storage buffer of `size` bytes (at least 4).
    pub fn new(ctx: &Context, size: u64, name: &str) -> Result<Self> {
        Self::with_location(ctx, size, name, MemoryLocation::GpuOnly)
    }

    fn with_location(ctx: &Context, size: u64, name: &str, loc: MemoryLocation) -> Result<Self> {
        ensure!(
            size > 0,
            "buffer {name:?}: size 0 (empty tensors are not allowed)"
        );
        let range = ctx.inner.info.max_storage_buffer_range;
        ensure!(
            loc != MemoryLocation::GpuOnly || size <= range,
            "buffer {name:?}: {size} bytes exceeds the device's maxStorageBufferRange ({range} bytes); \
             split the batch or use a smaller resolution"
        );
        // whole 16-byte units: a kernel may read the vec4 that holds any element (elementwise.wgsl binary4);
        // on devices that read through texel views, buffers of TEXEL_MIN_BYTES or more take whole image rows
        // (at most 16 KiB - 16 bytes more, plus the image's own padding: see `image::memory_requirements`) so
        // any of them can be viewed as an image
        let texel_sized = Self::texel_sized(ctx, size, loc);
        let size = if texel_sized {
            size.next_multiple_of(IMAGE_ROW_BYTES)
        } else {
            size.next_multiple_of(16)
        };
        let d = &ctx.inner.device;
        let bci = vk::BufferCreateInfo::default().size(size).usage(
            vk::BufferUsageFlags::STORAGE_BUFFER
                | vk::BufferUsageFlags::TRANSFER_SRC
                | vk::BufferUsageFlags::TRANSFER_DST,
        );
        // SAFETY: valid device and create info.
        let raw = unsafe { d.create_buffer(&bci, None) }.map_err(vk_err("vkCreateBuffer"))?;
        // SAFETY: raw is a fresh buffer of this device.
        let mut req = unsafe { d.get_buffer_memory_requirements(raw) };
        if texel_sized {
            // room for the texel view's image too (it may want a few rows more than the buffer)
            let ir = super::image::memory_requirements(d, size);
            req.size = req.size.max(ir.size);
            req.alignment = req.alignment.max(ir.alignment);
            req.memory_type_bits &= ir.memory_type_bits;
        }
        let alloc = {
            let mut a = ctx.inner.allocator.lock().expect("allocator lock");
            a.as_mut()
                .expect("allocator alive")
                .allocate(&AllocationCreateDesc {
                    name,
                    requirements: req,
                    location: loc,
                    linear: true,
                    allocation_scheme: AllocationScheme::GpuAllocatorManaged,
                })
        };
        let alloc = match alloc {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: the buffer is unused.
                unsafe { d.destroy_buffer(raw, None) };
                return Err(super::alloc_err(e))
                    .with_context(|| format!("allocating {size} bytes for buffer {name:?}"));
            }
        };
        // SAFETY: memory and offset come from the allocation made for this buffer's requirements.
        unsafe { d.bind_buffer_memory(raw, alloc.memory(), alloc.offset()) }
            .map_err(vk_err("vkBindBufferMemory"))?;
        ctx.set_name(raw, name);
        static NEXT_ID: AtomicU64 = AtomicU64::new(0);
        Ok(Self {
            ctx: ctx.inner.clone(),
            raw,
            id: BufferId(NEXT_ID.fetch_add(1, Ordering::Relaxed)),
            released: AtomicBool::new(false),
            alloc: Some(alloc),
            size,
            name: name.to_string(),
            texel_sized,
            texels: Mutex::new(None),
        })
    }

    fn texel_sized(ctx: &Context, size: u64, loc: MemoryLocation) -> bool {
        let i = &ctx.inner.info;
        i.linear_images && i.is_cpu() && loc == MemoryLocation::GpuOnly && size >= TEXEL_MIN_BYTES
    }

    /// Whether kernels can read this buffer through a storage-image binding (see `vk::image`): CPU devices
    /// with linear rgba32f storage images, buffers of at least [`TEXEL_MIN_BYTES`].
    pub fn has_texel_view(&self) -> bool {
        self.texel_sized
    }

    /// The storage-image view of the buffer's bytes (created on first use).
    pub(crate) fn texel_view(&self) -> Result<vk::ImageView> {
        ensure!(
            self.has_texel_view(),
            "buffer {:?} ({} bytes) cannot be read through an image on this device",
            self.name,
            self.size
        );
        let mut t = self.texels.lock().expect("texel view lock");
        if t.is_none() {
            let a = self.alloc.as_ref().expect("allocation alive");
            // SAFETY: memory handle of this buffer's live allocation.
            let mem = unsafe { a.memory() };
            *t = Some(TexelView::new(
                &self.ctx,
                mem,
                a.offset(),
                self.size,
                a.size(),
                &self.name,
            )?);
        }
        Ok(t.as_ref().expect("created").view)
    }

    pub fn size(&self) -> u64 {
        self.size
    }

    pub fn id(&self) -> BufferId {
        self.id
    }

    /// Marks the buffer as released by the pool that hands it out (`true`: its contents are dead until the
    /// pool hands it out again, `false`). In debug builds, recording a dispatch or copy that uses a released
    /// buffer is an error: a read after the last use that the pool was told about.
    pub fn set_released(&self, released: bool) {
        self.released.store(released, Ordering::Relaxed);
    }

    /// See [`Self::set_released`].
    pub fn is_released(&self) -> bool {
        self.released.load(Ordering::Relaxed)
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    fn host_coherent(&self) -> bool {
        let a = self.alloc.as_ref().expect("allocation alive");
        a.mapped_ptr().is_some()
            && a.memory_properties()
                .contains(vk::MemoryPropertyFlags::HOST_COHERENT)
    }

    /// Writes `data` at byte `offset`. The caller must ensure no GPU work is using the buffer.
    pub fn write(&self, ctx: &Context, offset: u64, data: &[u8]) -> Result<()> {
        ensure!(
            offset + data.len() as u64 <= self.size,
            "buffer {:?}: write past the end",
            self.name
        );
        if self.host_coherent() {
            self.write_mapped(offset, data);
            return Ok(());
        }
        let staging = Buffer::with_location(
            ctx,
            data.len() as u64,
            "staging-upload",
            MemoryLocation::CpuToGpu,
        )?;
        staging.write_mapped(0, data);
        let mut rec = ctx.recorder()?;
        rec.copy(&staging, 0, self, offset, data.len() as u64);
        rec.finish()?.submit_wait()?;
        Ok(())
    }

    fn write_mapped(&self, offset: u64, data: &[u8]) {
        let p = self
            .alloc
            .as_ref()
            .and_then(|a| a.mapped_ptr())
            .expect("mapped");
        // SAFETY: the mapping covers `size` bytes and the range was checked; the GPU is not using the buffer
        // (caller contract), and host-coherent or staging memory needs no flush.
        unsafe {
            std::ptr::copy_nonoverlapping(
                data.as_ptr(),
                (p.as_ptr() as *mut u8).add(offset as usize),
                data.len(),
            )
        };
    }

    /// Reads `len` bytes at byte `offset`. The caller must ensure GPU writes to the buffer have completed.
    pub fn read(&self, ctx: &Context, offset: u64, len: u64) -> Result<Vec<u8>> {
        ensure!(
            offset + len <= self.size,
            "buffer {:?}: read past the end",
            self.name
        );
        if self.host_coherent() {
            let s = self
                .alloc
                .as_ref()
                .and_then(|a| a.mapped_slice())
                .expect("mapped");
            return Ok(s[offset as usize..(offset + len) as usize].to_vec());
        }
        let staging =
            Buffer::with_location(ctx, len, "staging-download", MemoryLocation::GpuToCpu)?;
        let mut rec = ctx.recorder()?;
        rec.copy(self, offset, &staging, 0, len);
        rec.finish()?.submit_wait()?;
        let a = staging.alloc.as_ref().expect("alloc");
        if !a
            .memory_properties()
            .contains(vk::MemoryPropertyFlags::HOST_COHERENT)
        {
            let range = vk::MappedMemoryRange::default()
                // SAFETY: memory handle of a live allocation.
                .memory(unsafe { a.memory() })
                .offset(0)
                .size(vk::WHOLE_SIZE);
            // SAFETY: the range lies in mapped memory of this allocation.
            unsafe { ctx.inner.device.invalidate_mapped_memory_ranges(&[range]) }
                .map_err(vk_err("vkInvalidateMappedMemoryRanges"))?;
        }
        Ok(a.mapped_slice().expect("mapped")[..len as usize].to_vec())
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        if let Some(t) = self.texels.get_mut().ok().and_then(|t| t.take()) {
            // SAFETY: recordings keep an Arc of every buffer they use, so no pending GPU work uses the image.
            unsafe { t.destroy(&self.ctx.device) };
        }
        if let Some(a) = self.alloc.take() {
            if let Ok(mut al) = self.ctx.allocator.lock() {
                if let Some(al) = al.as_mut() {
                    let _ = al.free(a);
                }
            }
        }
        // SAFETY: recordings keep an Arc of every buffer they use, so no pending GPU work references it.
        unsafe { self.ctx.device.destroy_buffer(self.raw, None) };
    }
}
