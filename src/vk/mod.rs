//! The Vulkan layer: instance, device choice, memory, pipelines, command recording, timestamps.
//! `ash` is used only inside this folder. It knows nothing of tensors or models.
//!
//! Lifetime rule: [`Context`] is reference-counted; every buffer, pipeline and recording holds an `Arc` of the
//! shared device state, so the device outlives all of them, and the allocator is dropped before the device.
mod command;
mod device;
mod error;
mod image;
mod instance;
mod memory;
mod pipeline;

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use anyhow::{Context as _, Result};
use ash::vk;

pub use command::{Recorder, Recording, Timing};
pub use device::{scheduler_pin, DeviceId, DeviceInfo, Pin, NVIDIA_VENDOR_ID};
pub use error::VkError;
pub(crate) use error::{alloc_err, vk_err};
pub use image::{IMAGE_ROW_BYTES, IMAGE_ROW_TEXELS};
pub use instance::{validation_errors, validation_requested};
pub use memory::{Buffer, BufferId, TEXEL_MIN_BYTES};

use crate::kernels::KernelId;

/// Texel views unless `B2DR_TEXEL_VIEWS=0`.
fn texel_views_env() -> bool {
    std::env::var("B2DR_TEXEL_VIEWS").map_or(true, |v| v != "0")
}

/// Options for creating a [`Context`].
#[derive(Clone, Debug, Default)]
pub struct ContextOptions {
    /// Device index or name substring; default: `B2DR_DEVICE`, else discrete > integrated > CPU.
    pub device: Option<String>,
    /// Enable the Khronos validation layer; default: `B2DR_VALIDATION=1`.
    pub validation: Option<bool>,
    /// Every recorder writes a GPU timestamp after each dispatch (per-op profiles, `--profile`).
    pub profile: bool,
    /// Read large buffers through texel views where the device has them (`DeviceInfo::linear_images`);
    /// default: on unless `B2DR_TEXEL_VIEWS=0`. Results are bitwise the same either way.
    pub texel_views: Option<bool>,
}

/// Handles a library user passes in to run b2dr on their own Vulkan objects ("explicit Vulkan control").
/// The device must have been created with the features listed by [`ExternalVulkan::required_features`] when
/// f16 kernels are wanted; b2dr never destroys these objects.
pub struct ExternalVulkan {
    pub entry: ash::Entry,
    pub instance: ash::Instance,
    pub physical_device: vk::PhysicalDevice,
    pub device: ash::Device,
    pub queue: vk::Queue,
    pub queue_family: u32,
    /// Whether the device was created with shaderFloat16 + storageBuffer16BitAccess enabled.
    pub f16_enabled: bool,
}

impl ExternalVulkan {
    /// Features b2dr's f16 kernels need enabled at device creation (Vulkan 1.1/1.2 feature names).
    pub fn required_features() -> &'static [&'static str] {
        &[
            "storageBuffer16BitAccess (Vulkan 1.1)",
            "uniformAndStorageBuffer16BitAccess (Vulkan 1.1)",
            "shaderFloat16 (Vulkan 1.2)",
        ]
    }
}

pub(crate) struct Inner {
    _entry: ash::Entry,
    pub instance: ash::Instance,
    debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    #[allow(dead_code)]
    // kept for users of the raw handles (explicit Vulkan control) and future queries
    pub physical: vk::PhysicalDevice,
    pub device: ash::Device,
    pub queue: Mutex<vk::Queue>,
    pub queue_family: u32,
    pub allocator: Mutex<Option<gpu_allocator::vulkan::Allocator>>,
    pub pipelines: Mutex<HashMap<KernelId, Arc<pipeline::Pipeline>>>,
    pub info: DeviceInfo,
    pub debug_utils: Option<ash::ext::debug_utils::Device>,
    owned: bool,
    pub validation: bool,
    pub profile: bool,
}

/// A Vulkan device ready for b2dr's kernels. Cheap to clone.
#[derive(Clone)]
pub struct Context {
    pub(crate) inner: Arc<Inner>,
}

impl Context {
    /// Creates an instance and device (see [`ContextOptions`]).
    pub fn new(opts: &ContextOptions) -> Result<Self> {
        let validation = opts.validation.unwrap_or_else(validation_requested);
        let parts = instance::create_instance(validation)?;
        let devices = device::list(&parts.instance)?;
        let sel = opts
            .device
            .clone()
            .or_else(|| std::env::var("B2DR_DEVICE").ok());
        let (pd, mut info) = device::choose(&devices, sel.as_deref())?;
        info.linear_images &= opts.texel_views.unwrap_or_else(texel_views_env);
        let family = device::compute_queue_family(&parts.instance, pd)?;
        let dev = device::create_device(&parts.instance, pd, &info, family)?;
        // SAFETY: the queue family index was used at device creation with one queue.
        let queue = unsafe { dev.get_device_queue(family, 0) };
        let debug_utils = parts
            .debug
            .as_ref()
            .map(|_| ash::ext::debug_utils::Device::new(&parts.instance, &dev));
        let mut c = Self::assemble(
            parts.entry,
            parts.instance,
            parts.debug,
            pd,
            dev,
            queue,
            family,
            info,
            true,
            parts.validation,
            debug_utils,
        )?;
        if let Some(inner) = Arc::get_mut(&mut c.inner) {
            inner.profile = opts.profile;
        }
        Ok(c)
    }

    /// Uses a caller's instance, device and queue. b2dr creates its own allocator, command pool and pipelines
    /// on that device and destroys only those.
    pub fn from_external(ext: ExternalVulkan) -> Result<Self> {
        let mut info = device::describe(&ext.instance, ext.physical_device, 0);
        info.f16 &= ext.f16_enabled;
        info.linear_images &= texel_views_env();
        info.cooperative_matrix = false; // only when b2dr enabled the extension itself
        Self::assemble(
            ext.entry,
            ext.instance,
            None,
            ext.physical_device,
            ext.device,
            ext.queue,
            ext.queue_family,
            info,
            false,
            false,
            None,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        entry: ash::Entry,
        instance: ash::Instance,
        debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
        physical: vk::PhysicalDevice,
        device: ash::Device,
        queue: vk::Queue,
        queue_family: u32,
        info: DeviceInfo,
        owned: bool,
        validation: bool,
        debug_utils: Option<ash::ext::debug_utils::Device>,
    ) -> Result<Self> {
        let allocator =
            gpu_allocator::vulkan::Allocator::new(&gpu_allocator::vulkan::AllocatorCreateDesc {
                instance: instance.clone(),
                device: device.clone(),
                physical_device: physical,
                debug_settings: Default::default(),
                buffer_device_address: false,
                allocation_sizes: Default::default(),
            })
            .context("creating the gpu-allocator")?;
        Ok(Self {
            inner: Arc::new(Inner {
                _entry: entry,
                instance,
                debug,
                physical,
                device,
                queue: Mutex::new(queue),
                queue_family,
                allocator: Mutex::new(Some(allocator)),
                pipelines: Mutex::new(HashMap::new()),
                info,
                debug_utils,
                owned,
                validation,
                profile: false,
            }),
        })
    }

    /// The chosen device.
    pub fn info(&self) -> &DeviceInfo {
        &self.inner.info
    }

    /// Whether the validation layer is active on this context.
    pub fn validation_enabled(&self) -> bool {
        self.inner.validation
    }

    /// All physical devices visible to a fresh instance (for `b2dr info`).
    pub fn list_devices() -> Result<Vec<DeviceInfo>> {
        let parts = instance::create_instance(false)?;
        let l = device::list(&parts.instance).map(|v| v.into_iter().map(|(_, d)| d).collect());
        // SAFETY: nothing else uses this temporary instance.
        unsafe { parts.instance.destroy_instance(None) };
        l
    }

    /// Bytes currently allocated through gpu-allocator (device memory in use by b2dr).
    pub fn allocated_bytes(&self) -> u64 {
        let a = self.inner.allocator.lock().expect("allocator lock");
        a.as_ref()
            .map(|a| a.generate_report().total_allocated_bytes)
            .unwrap_or(0)
    }

    /// Waits until the device is idle.
    pub fn wait_idle(&self) -> Result<()> {
        let _q = self.inner.queue.lock().expect("queue lock");
        // SAFETY: the queue mutex is held, so no submit runs concurrently.
        unsafe { self.inner.device.device_wait_idle() }.map_err(vk_err("vkDeviceWaitIdle"))
    }

    pub(crate) fn set_name<H: vk::Handle>(&self, handle: H, name: &str) {
        if let Some(du) = &self.inner.debug_utils {
            if let Ok(cname) = std::ffi::CString::new(name) {
                let ni = vk::DebugUtilsObjectNameInfoEXT::default()
                    .object_handle(handle)
                    .object_name(&cname);
                // SAFETY: the handle belongs to this device; naming is advisory.
                let _ = unsafe { du.set_debug_utils_object_name(&ni) };
            }
        }
    }
}

impl Drop for Inner {
    fn drop(&mut self) {
        // SAFETY: last reference: no buffer, pipeline or recording is alive (each holds an Arc of Inner).
        unsafe {
            let _ = self.device.device_wait_idle();
            for (_, p) in self
                .pipelines
                .lock()
                .map(|mut m| std::mem::take(&mut *m))
                .unwrap_or_default()
            {
                if let Ok(p) = Arc::try_unwrap(p) {
                    p.destroy(&self.device);
                }
            }
            // The allocator must go before the device.
            if let Ok(mut a) = self.allocator.lock() {
                a.take();
            }
            if self.owned {
                self.device.destroy_device(None);
                if let Some((du, m)) = self.debug.take() {
                    du.destroy_debug_utils_messenger(m, None);
                }
                self.instance.destroy_instance(None);
            }
        }
    }
}
