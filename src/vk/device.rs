//! Physical-device choice and logical-device creation.
use std::ffi::CStr;

use anyhow::{bail, Result};
use ash::vk;

use super::vk_err;

/// What b2dr knows about a physical device.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    pub index: usize,
    pub name: String,
    pub kind: String,
    pub api_version: String,
    pub driver: String,
    /// f16 arithmetic (shaderFloat16) and 16-bit storage-buffer access.
    pub f16: bool,
    /// Subgroup basic + arithmetic + shuffle in compute shaders.
    pub subgroup: bool,
    pub subgroup_size: u32,
    /// VK_KHR_cooperative_matrix (tensor cores).
    pub cooperative_matrix: bool,
    pub max_storage_buffer_range: u64,
    pub max_shared_memory: u32,
    pub max_push_constants: u32,
    pub timestamp_period_ns: f32,
    pub timestamps: bool,
    /// Linear-tiled rgba32f storage images of 16384 x 16384 texels: kernels can read a buffer through a storage
    /// image aliasing its memory ([`crate::vk::IMAGE_ROW_TEXELS`] texels a row); used on CPU devices, where
    /// an image load fetches a whole texel per lane (see `Buffer::texel_view`). Off with
    /// `ContextOptions::texel_views` = false or `B2DR_TEXEL_VIEWS=0` (A/B measurements, or a driver that
    /// misbehaves).
    pub linear_images: bool,
}

impl DeviceInfo {
    /// A CPU implementation (lavapipe): the ops pick the paths measured fastest there.
    pub fn is_cpu(&self) -> bool {
        self.kind == "CPU"
    }
}

fn rank(t: vk::PhysicalDeviceType) -> u32 {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => 0,
        vk::PhysicalDeviceType::INTEGRATED_GPU => 1,
        vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
        vk::PhysicalDeviceType::CPU => 3,
        _ => 4,
    }
}

fn kind_name(t: vk::PhysicalDeviceType) -> &'static str {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => "discrete GPU",
        vk::PhysicalDeviceType::INTEGRATED_GPU => "integrated GPU",
        vk::PhysicalDeviceType::VIRTUAL_GPU => "virtual GPU",
        vk::PhysicalDeviceType::CPU => "CPU",
        _ => "other",
    }
}

/// Describes one physical device.
pub(super) fn describe(
    instance: &ash::Instance,
    pd: vk::PhysicalDevice,
    index: usize,
) -> DeviceInfo {
    let mut v11 = vk::PhysicalDeviceVulkan11Features::default();
    let mut v12 = vk::PhysicalDeviceVulkan12Features::default();
    let mut f2 = vk::PhysicalDeviceFeatures2::default()
        .push_next(&mut v11)
        .push_next(&mut v12);
    let mut sg = vk::PhysicalDeviceSubgroupProperties::default();
    let mut p2 = vk::PhysicalDeviceProperties2::default().push_next(&mut sg);
    // SAFETY: queries on a valid physical device with correctly chained structs.
    let (exts, qf) = unsafe {
        instance.get_physical_device_features2(pd, &mut f2);
        instance.get_physical_device_properties2(pd, &mut p2);
        (
            instance
                .enumerate_device_extension_properties(pd)
                .unwrap_or_default(),
            instance.get_physical_device_queue_family_properties(pd),
        )
    };
    let p = p2.properties;
    // SAFETY: plain query on a valid physical device.
    let fmt = unsafe {
        instance.get_physical_device_format_properties(pd, vk::Format::R32G32B32A32_SFLOAT)
    };
    let has_ext = |n: &CStr| exts.iter().any(|e| e.extension_name_as_c_str() == Ok(n));
    let needed = vk::SubgroupFeatureFlags::BASIC
        | vk::SubgroupFeatureFlags::ARITHMETIC
        | vk::SubgroupFeatureFlags::SHUFFLE;
    let v = p.api_version;
    DeviceInfo {
        index,
        name: p
            .device_name_as_c_str()
            .map(|c| c.to_string_lossy().into_owned())
            .unwrap_or_default(),
        kind: kind_name(p.device_type).to_string(),
        api_version: format!(
            "{}.{}.{}",
            vk::api_version_major(v),
            vk::api_version_minor(v),
            vk::api_version_patch(v)
        ),
        driver: format!("{:#x}", p.driver_version),
        // naga declares UniformAndStorageBuffer16BitAccess for f16 storage buffers, so both 16-bit features are needed.
        f16: v12.shader_float16 == vk::TRUE
            && v11.storage_buffer16_bit_access == vk::TRUE
            && v11.uniform_and_storage_buffer16_bit_access == vk::TRUE,
        subgroup: sg.supported_stages.contains(vk::ShaderStageFlags::COMPUTE)
            && sg.supported_operations.contains(needed),
        subgroup_size: sg.subgroup_size,
        cooperative_matrix: has_ext(ash::khr::cooperative_matrix::NAME),
        max_storage_buffer_range: p.limits.max_storage_buffer_range as u64,
        max_shared_memory: p.limits.max_compute_shared_memory_size,
        max_push_constants: p.limits.max_push_constants_size,
        timestamp_period_ns: p.limits.timestamp_period,
        timestamps: p.limits.timestamp_compute_and_graphics == vk::TRUE
            || qf.iter().any(|q| {
                q.queue_flags.contains(vk::QueueFlags::COMPUTE) && q.timestamp_valid_bits > 0
            }),
        linear_images: fmt
            .linear_tiling_features
            .contains(vk::FormatFeatureFlags::STORAGE_IMAGE)
            && p.limits.max_image_dimension2_d >= 16384,
    }
}

/// Lists all physical devices.
pub(super) fn list(instance: &ash::Instance) -> Result<Vec<(vk::PhysicalDevice, DeviceInfo)>> {
    // SAFETY: valid instance.
    let pds = unsafe { instance.enumerate_physical_devices() }
        .map_err(vk_err("vkEnumeratePhysicalDevices"))?;
    Ok(pds
        .into_iter()
        .enumerate()
        .map(|(i, pd)| (pd, describe(instance, pd, i)))
        .collect())
}

/// Chooses a device: `selector` (index or case-insensitive name substring) if given, else discrete GPU first,
/// then integrated, then virtual, then CPU (lavapipe).
pub(super) fn choose(
    instance: &ash::Instance,
    devices: &[(vk::PhysicalDevice, DeviceInfo)],
    selector: Option<&str>,
) -> Result<(vk::PhysicalDevice, DeviceInfo)> {
    if devices.is_empty() {
        bail!("no Vulkan device found; for a CPU device install lavapipe: apt-get install mesa-vulkan-drivers");
    }
    if let Some(sel) = selector.filter(|s| !s.is_empty()) {
        let found = match sel.parse::<usize>() {
            Ok(i) => devices.get(i),
            Err(_) => devices
                .iter()
                .find(|(_, d)| d.name.to_lowercase().contains(&sel.to_lowercase())),
        };
        let names: Vec<String> = devices
            .iter()
            .map(|(_, d)| format!("{}: {}", d.index, d.name))
            .collect();
        return found.cloned().ok_or_else(|| {
            anyhow::anyhow!(
                "no Vulkan device matches {sel:?}; available: {}",
                names.join(", ")
            )
        });
    }
    let mut best = devices.to_vec();
    // SAFETY: valid instance and physical devices.
    best.sort_by_key(|(pd, d)| {
        (
            rank(unsafe { instance.get_physical_device_properties(*pd) }.device_type),
            d.index,
        )
    });
    Ok(best.remove(0))
}

/// The index of a queue family with compute support.
pub(super) fn compute_queue_family(
    instance: &ash::Instance,
    pd: vk::PhysicalDevice,
) -> Result<u32> {
    // SAFETY: valid physical device.
    let qf = unsafe { instance.get_physical_device_queue_family_properties(pd) };
    // Prefer a compute queue family (dedicated async compute is not needed; any compute family works).
    qf.iter()
        .position(|q| q.queue_flags.contains(vk::QueueFlags::COMPUTE))
        .map(|i| i as u32)
        .ok_or_else(|| anyhow::anyhow!("the chosen Vulkan device has no compute queue"))
}

/// Creates the logical device with the features b2dr uses (those the device has).
pub(super) fn create_device(
    instance: &ash::Instance,
    pd: vk::PhysicalDevice,
    info: &DeviceInfo,
    family: u32,
) -> Result<ash::Device> {
    let prio = [1.0f32];
    let qci = [vk::DeviceQueueCreateInfo::default()
        .queue_family_index(family)
        .queue_priorities(&prio)];
    let mut v11 = vk::PhysicalDeviceVulkan11Features::default()
        .storage_buffer16_bit_access(info.f16)
        .uniform_and_storage_buffer16_bit_access(info.f16);
    let mut v12 = vk::PhysicalDeviceVulkan12Features::default().shader_float16(info.f16);
    let mut coop =
        vk::PhysicalDeviceCooperativeMatrixFeaturesKHR::default().cooperative_matrix(true);
    let mut exts = vec![];
    let mut ci = vk::DeviceCreateInfo::default()
        .queue_create_infos(&qci)
        .push_next(&mut v11)
        .push_next(&mut v12);
    if info.cooperative_matrix {
        exts.push(ash::khr::cooperative_matrix::NAME.as_ptr());
        ci = ci.push_next(&mut coop);
    }
    let ci = ci.enabled_extension_names(&exts);
    // SAFETY: the create info chain lives until the call returns.
    unsafe { instance.create_device(pd, &ci, None) }.map_err(vk_err("vkCreateDevice"))
}
