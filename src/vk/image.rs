//! Storage-image views of buffers ("texel views"): a linear-tiled rgba32f image bound to a buffer's own memory,
//! [`IMAGE_ROW_TEXELS`] texels (16 KiB) a row, so texel t of the image is bytes 16 t .. 16 t + 15 of the buffer.
//! Kernels declare such a binding as `texture_storage_2d<rgba32float, read>` and read vec4 t at
//! `(t % 1024, t / 1024)` (`texel_xy` in common.wgsl); the launcher binds the buffer itself. 16 KiB rows keep
//! the padding small (lavapipe also rounds a linear image's height up to a multiple of 4 rows) and still reach
//! 256 MiB at the 16384-row limit, more than maxStorageBufferRange.
//!
//! Why: lavapipe 22.3 compiles every storage-buffer load to a loop over the 8 lanes with one bounds-checked
//! scalar load per component, but an image load to one 16-byte fetch per lane. Measured here (2026-11-23,
//! 262144 invocations x 16 vec4 loads, 64 MiB): buffer 5.5-5.7 ms, image 2.2-2.5 ms. Image *stores* are slower
//! than buffer stores (35 vs 4-9 ms), so kernels keep writing the buffer and only read through the image.
//! Writes through the buffer are visible to the image after the recorder's global memory barrier (the same
//! memory); the image is created in PREINITIALIZED layout (contents preserved) and moved to GENERAL once.
use anyhow::{ensure, Result};
use ash::vk;

use super::{vk_err, Inner};

/// Texels per image row (16 bytes each): 16 KiB rows (`texel_xy` in kernels/common.wgsl matches).
pub const IMAGE_ROW_TEXELS: u64 = 1024;
/// Bytes per image row; buffers that can be viewed as images have sizes that are multiples of this.
pub const IMAGE_ROW_BYTES: u64 = IMAGE_ROW_TEXELS * 16;

pub(crate) struct TexelView {
    pub image: vk::Image,
    pub view: vk::ImageView,
}

impl TexelView {
    /// Creates the image over the first `size` bytes (a multiple of [`IMAGE_ROW_BYTES`]) of `memory` at
    /// `offset`, where `avail` bytes belong to the buffer's allocation (the driver may want more than `size`
    /// for the image: see [`memory_requirements`]).
    pub fn new(
        inner: &Inner,
        memory: vk::DeviceMemory,
        offset: u64,
        size: u64,
        avail: u64,
        name: &str,
    ) -> Result<Self> {
        ensure!(
            size % IMAGE_ROW_BYTES == 0 && size > 0,
            "buffer {name:?}: {size} bytes is not a whole number of image rows"
        );
        let d = &inner.device;
        let ci = create_info(size);
        // SAFETY: valid device and create info.
        let image = unsafe { d.create_image(&ci, None) }.map_err(vk_err("vkCreateImage"))?;
        let destroy = |e: anyhow::Error| {
            // SAFETY: the image is unused.
            unsafe { d.destroy_image(image, None) };
            e
        };
        // SAFETY: queries on the fresh image.
        let (req, layout) = unsafe {
            (
                d.get_image_memory_requirements(image),
                d.get_image_subresource_layout(
                    image,
                    vk::ImageSubresource {
                        aspect_mask: vk::ImageAspectFlags::COLOR,
                        mip_level: 0,
                        array_layer: 0,
                    },
                ),
            )
        };
        // the texel <-> byte mapping the kernels assume, and the image inside the buffer's memory
        if req.size > avail
            || offset % req.alignment.max(1) != 0
            || layout.offset != 0
            || layout.row_pitch != IMAGE_ROW_BYTES
        {
            return Err(destroy(anyhow::anyhow!(
                "buffer {name:?} ({size} bytes, {avail} allocated at {offset}): the driver's linear image layout (size {}, alignment {}, offset {}, row pitch \
                 {}) does not match the buffer's bytes",
                req.size,
                req.alignment,
                layout.offset,
                layout.row_pitch
            )));
        }
        // SAFETY: the memory range lies in the buffer's allocation (checked above).
        unsafe { d.bind_image_memory(image, memory, offset) }
            .map_err(vk_err("vkBindImageMemory"))
            .map_err(destroy)?;
        let range = vk::ImageSubresourceRange {
            aspect_mask: vk::ImageAspectFlags::COLOR,
            base_mip_level: 0,
            level_count: 1,
            base_array_layer: 0,
            layer_count: 1,
        };
        let vci = vk::ImageViewCreateInfo::default()
            .image(image)
            .view_type(vk::ImageViewType::TYPE_2D)
            .format(vk::Format::R32G32B32A32_SFLOAT)
            .subresource_range(range);
        // SAFETY: valid image bound to memory.
        let view = unsafe { d.create_image_view(&vci, None) }
            .map_err(vk_err("vkCreateImageView"))
            .map_err(destroy)?;
        let tv = Self { image, view };
        if let Err(e) = to_general(inner, image, range) {
            // SAFETY: nothing uses the image yet.
            unsafe { tv.destroy(d) };
            return Err(e);
        }
        Ok(tv)
    }

    /// # Safety
    /// No pending GPU work may use the image.
    pub unsafe fn destroy(&self, d: &ash::Device) {
        // SAFETY: caller contract.
        unsafe {
            d.destroy_image_view(self.view, None);
            d.destroy_image(self.image, None);
        }
    }
}

fn create_info(size: u64) -> vk::ImageCreateInfo<'static> {
    vk::ImageCreateInfo::default()
        .image_type(vk::ImageType::TYPE_2D)
        .format(vk::Format::R32G32B32A32_SFLOAT)
        .extent(vk::Extent3D {
            width: IMAGE_ROW_TEXELS as u32,
            height: (size / IMAGE_ROW_BYTES) as u32,
            depth: 1,
        })
        .mip_levels(1)
        .array_layers(1)
        .samples(vk::SampleCountFlags::TYPE_1)
        .tiling(vk::ImageTiling::LINEAR)
        .usage(vk::ImageUsageFlags::STORAGE)
        .initial_layout(vk::ImageLayout::PREINITIALIZED)
}

/// What the texel view of a buffer of `size` bytes needs of its memory (lavapipe pads linear images to
/// whole blocks of rows, so this can exceed `size`); the buffer's allocation covers it.
pub(crate) fn memory_requirements(d: &ash::Device, size: u64) -> vk::MemoryRequirements {
    let ci = create_info(size);
    let info = vk::DeviceImageMemoryRequirements::default().create_info(&ci);
    let mut out = vk::MemoryRequirements2::default();
    // SAFETY: valid device (Vulkan 1.3 core query) and create info.
    unsafe { d.get_device_image_memory_requirements(&info, &mut out) };
    out.memory_requirements
}

/// PREINITIALIZED -> GENERAL in a one-off submit (the layout storage-image descriptors need).
fn to_general(inner: &Inner, image: vk::Image, range: vk::ImageSubresourceRange) -> Result<()> {
    let d = &inner.device;
    let pci = vk::CommandPoolCreateInfo::default().queue_family_index(inner.queue_family);
    // SAFETY: valid device; the pool, command buffer and fence are used by this function only and destroyed
    // after the wait.
    unsafe {
        let pool = d
            .create_command_pool(&pci, None)
            .map_err(vk_err("vkCreateCommandPool"))?;
        let run = || -> Result<()> {
            let ai = vk::CommandBufferAllocateInfo::default()
                .command_pool(pool)
                .level(vk::CommandBufferLevel::PRIMARY)
                .command_buffer_count(1);
            let cmd = d
                .allocate_command_buffers(&ai)
                .map_err(vk_err("vkAllocateCommandBuffers"))?[0];
            d.begin_command_buffer(cmd, &vk::CommandBufferBeginInfo::default())
                .map_err(vk_err("vkBeginCommandBuffer"))?;
            let ib = [vk::ImageMemoryBarrier::default()
                .image(image)
                .old_layout(vk::ImageLayout::PREINITIALIZED)
                .new_layout(vk::ImageLayout::GENERAL)
                .src_access_mask(vk::AccessFlags::HOST_WRITE)
                .dst_access_mask(vk::AccessFlags::SHADER_READ)
                .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
                .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
                .subresource_range(range)];
            d.cmd_pipeline_barrier(
                cmd,
                vk::PipelineStageFlags::HOST,
                vk::PipelineStageFlags::COMPUTE_SHADER,
                vk::DependencyFlags::empty(),
                &[],
                &[],
                &ib,
            );
            d.end_command_buffer(cmd)
                .map_err(vk_err("vkEndCommandBuffer"))?;
            let fence = d
                .create_fence(&vk::FenceCreateInfo::default(), None)
                .map_err(vk_err("vkCreateFence"))?;
            let cmds = [cmd];
            let si = [vk::SubmitInfo::default().command_buffers(&cmds)];
            let r = {
                let q = inner.queue.lock().expect("queue lock");
                d.queue_submit(*q, &si, fence)
                    .map_err(vk_err("vkQueueSubmit"))
            }
            .and_then(|_| {
                d.wait_for_fences(&[fence], true, u64::MAX)
                    .map_err(vk_err("vkWaitForFences"))
            });
            d.destroy_fence(fence, None);
            r
        };
        let r = run();
        d.destroy_command_pool(pool, None);
        r
    }
}
