//! Physical-device choice and logical-device creation.
use std::ffi::CStr;

use anyhow::{bail, Context as _, Result};
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
    /// `VkPhysicalDeviceDriverProperties` driverName and driverInfo, e.g. "llvmpipe: Mesa 25.0.7-2~bpo12+1
    /// (LLVM 15.0.6)": which driver build runs (the tests print it, so a log tells Mesa 22 from Mesa 25).
    pub driver_info: String,
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
    /// Vendor, deviceUUID and PCI address: what the scheduler's GPU is matched against.
    pub id: DeviceId,
    /// How the device was chosen (for `b2dr info` and the logs): the selector, the scheduler's variable, or
    /// the default ranking. Empty in a device list.
    pub selected_by: String,
}

/// The identity of a physical device: `VkPhysicalDeviceIDProperties::deviceUUID` (on NVIDIA the GPU UUID that
/// nvidia-smi, CUDA_VISIBLE_DEVICES and NVIDIA_VISIBLE_DEVICES show as `GPU-<uuid>`), the vendor ID and the
/// PCI address (domain, bus, device, function) where VK_EXT_pci_bus_info gives it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DeviceId {
    pub vendor_id: u32,
    pub uuid: [u8; 16],
    pub pci: Option<[u32; 4]>,
}

/// PCI vendor ID of NVIDIA, whose GPUs CUDA_VISIBLE_DEVICES / NVIDIA_VISIBLE_DEVICES ordinals count.
pub const NVIDIA_VENDOR_ID: u32 = 0x10de;

impl DeviceId {
    /// The UUID as 8-4-4-4-12 lowercase hex; NVIDIA devices with the `GPU-` prefix, as nvidia-smi -L prints.
    pub fn uuid_string(&self) -> String {
        let h: String = self.uuid.iter().map(|b| format!("{b:02x}")).collect();
        let u = format!(
            "{}-{}-{}-{}-{}",
            &h[0..8],
            &h[8..12],
            &h[12..16],
            &h[16..20],
            &h[20..32]
        );
        if self.vendor_id == NVIDIA_VENDOR_ID {
            format!("GPU-{u}")
        } else {
            u
        }
    }
    pub fn is_nvidia(&self) -> bool {
        self.vendor_id == NVIDIA_VENDOR_ID
    }
}

const ICD_HINT: &str =
    " (no NVIDIA device at all: in a container, is the NVIDIA Vulkan driver there? \
NVIDIA_DRIVER_CAPABILITIES must include graphics)";

/// What the scheduler's environment says about the GPU of this process (see [`scheduler_pin`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Pin {
    /// No variable set (or `all`): the default ranking.
    Unpinned,
    /// The device at this position of the list, and why ("CUDA_VISIBLE_DEVICES=...").
    Device(usize, String),
    /// The variable is set but names no GPU (empty, `none`, `void`, `NoDevFiles`, `-1`): NVIDIA devices are
    /// left alone (another process has them) and the default ranking picks among the others.
    NoGpu(String),
}

/// The device matching the scheduler's GPU assignment, from `CUDA_VISIBLE_DEVICES` (Slurm's GRES, Ray's
/// `num_gpus`), else `NVIDIA_VISIBLE_DEVICES` (the NVIDIA container runtime, Kubernetes' device plugin).
/// `env` reads a variable. The first entry of the list is this process's GPU (CUDA's device 0):
/// - a UUID (`GPU-8-4-4-4-12` hex, the prefix optional) matches `deviceUUID`;
/// - an ordinal `i` is the i-th NVIDIA device in PCI-address order (nvidia-smi's index; CUDA's too with
///   `CUDA_DEVICE_ORDER=PCI_BUS_ID`, and on nodes of one GPU model); when fewer NVIDIA devices are visible
///   than `i + 1` but exactly as many as the list names, the runtime has already hidden the others (cgroups,
///   containers) and the list's first entry is the first visible one.
///
/// Errors name the variable, its value and the devices' UUIDs.
pub fn scheduler_pin(devices: &[DeviceId], env: &dyn Fn(&str) -> Option<String>) -> Result<Pin> {
    let Some((var, value)) = ["CUDA_VISIBLE_DEVICES", "NVIDIA_VISIBLE_DEVICES"]
        .into_iter()
        .find_map(|v| env(v).map(|x| (v, x)))
    else {
        return Ok(Pin::Unpinned);
    };
    let what = format!("{var}={value}");
    let entries: Vec<&str> = value
        .split(',')
        .map(str::trim)
        .filter(|e| !e.is_empty())
        .collect();
    let Some(&first) = entries.first() else {
        return Ok(Pin::NoGpu(what));
    };
    match first.to_ascii_lowercase().as_str() {
        "all" => return Ok(Pin::Unpinned),
        "none" | "void" | "nodevfiles" | "-1" => return Ok(Pin::NoGpu(what)),
        _ => {}
    }
    let listing = || {
        let l: Vec<String> = devices
            .iter()
            .enumerate()
            .map(|(i, d)| format!("{i}: {}", d.uuid_string()))
            .collect();
        if l.is_empty() {
            "none".to_string()
        } else {
            l.join(", ")
        }
    };
    if let Ok(ordinal) = first.parse::<usize>() {
        let mut nvidia: Vec<usize> = (0..devices.len())
            .filter(|&i| devices[i].is_nvidia())
            .collect();
        if nvidia.iter().all(|&i| devices[i].pci.is_some()) {
            nvidia.sort_by_key(|&i| devices[i].pci);
        }
        let pos = if ordinal < nvidia.len() {
            Some(ordinal)
        } else if !nvidia.is_empty() && nvidia.len() == entries.len() {
            Some(0)
        } else {
            None
        };
        return match pos {
            Some(p) => Ok(Pin::Device(nvidia[p], what)),
            None => bail!(
                "{what}: GPU ordinal {ordinal}, but {} NVIDIA Vulkan device(s) are visible (devices: {}); \
                 give --device or B2DR_DEVICE{}",
                nvidia.len(),
                listing(),
                ICD_HINT
            ),
        };
    }
    if first.to_ascii_lowercase().starts_with("mig-") {
        bail!("{what}: a MIG instance; Vulkan does not run on MIG instances (give --device to choose another device)");
    }
    let hex: String = first
        .strip_prefix("GPU-")
        .or_else(|| first.strip_prefix("gpu-"))
        .unwrap_or(first)
        .chars()
        .filter(|c| *c != '-')
        .collect::<String>()
        .to_ascii_lowercase();
    let want = (hex.len() == 32)
        .then(|| {
            (0..16)
                .map(|i| u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).ok())
                .collect::<Option<Vec<u8>>>()
        })
        .flatten();
    let Some(want) = want else {
        bail!(
            "{what}: {first:?} is neither a GPU ordinal nor a GPU UUID (GPU-xxxxxxxx-xxxx-xxxx-xxxx-xxxxxxxxxxxx)"
        );
    };
    match devices.iter().position(|d| d.uuid[..] == want[..]) {
        Some(i) => Ok(Pin::Device(i, what)),
        None => bail!(
            "{what}: no Vulkan device has UUID {first} (devices: {}); give --device or B2DR_DEVICE{}",
            listing(),
            ICD_HINT
        ),
    }
}

impl DeviceInfo {
    /// A CPU implementation (lavapipe): the ops pick the paths measured fastest there.
    pub fn is_cpu(&self) -> bool {
        self.kind == "CPU"
    }
}

fn rank_name(kind: &str) -> u32 {
    match kind {
        "discrete GPU" => 0,
        "integrated GPU" => 1,
        "virtual GPU" => 2,
        "CPU" => 3,
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
    // SAFETY: plain query on a valid physical device.
    let exts = unsafe { instance.enumerate_device_extension_properties(pd) }.unwrap_or_default();
    let has_pci = exts
        .iter()
        .any(|e| e.extension_name_as_c_str() == Ok(ash::ext::pci_bus_info::NAME));
    let mut sg = vk::PhysicalDeviceSubgroupProperties::default();
    let mut idp = vk::PhysicalDeviceIDProperties::default();
    let mut drv = vk::PhysicalDeviceDriverProperties::default();
    let mut pci = vk::PhysicalDevicePCIBusInfoPropertiesEXT::default();
    let mut p2 = vk::PhysicalDeviceProperties2::default()
        .push_next(&mut sg)
        .push_next(&mut idp)
        .push_next(&mut drv);
    if has_pci {
        p2 = p2.push_next(&mut pci);
    }
    // SAFETY: queries on a valid physical device with correctly chained structs (the PCI struct only where
    // the device has the extension).
    let qf = unsafe {
        instance.get_physical_device_features2(pd, &mut f2);
        instance.get_physical_device_properties2(pd, &mut p2);
        instance.get_physical_device_queue_family_properties(pd)
    };
    let p = p2.properties;
    let id = DeviceId {
        vendor_id: p.vendor_id,
        uuid: idp.device_uuid,
        pci: has_pci.then_some([
            pci.pci_domain,
            pci.pci_bus,
            pci.pci_device,
            pci.pci_function,
        ]),
    };
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
        driver_info: {
            let name = drv
                .driver_name_as_c_str()
                .map(|c| c.to_string_lossy().into_owned());
            let info = drv
                .driver_info_as_c_str()
                .map(|c| c.to_string_lossy().into_owned());
            match (name.unwrap_or_default(), info.unwrap_or_default()) {
                (n, i) if n.is_empty() => i,
                (n, i) if i.is_empty() => n,
                (n, i) => format!("{n}: {i}"),
            }
        },
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
        id,
        selected_by: String::new(),
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

/// Chooses a device: `selector` (index or case-insensitive name substring) if given; else the device of the
/// scheduler's GPU ([`scheduler_pin`]: CUDA_VISIBLE_DEVICES / NVIDIA_VISIBLE_DEVICES); else discrete GPU
/// first, then integrated, then virtual, then CPU (lavapipe).
pub(super) fn choose(
    devices: &[(vk::PhysicalDevice, DeviceInfo)],
    selector: Option<&str>,
) -> Result<(vk::PhysicalDevice, DeviceInfo)> {
    if devices.is_empty() {
        bail!("no Vulkan device found; for a CPU device install lavapipe: apt-get install mesa-vulkan-drivers");
    }
    let picked = |i: usize, why: String| {
        let (pd, mut d) = devices[i].clone();
        d.selected_by = why;
        (pd, d)
    };
    if let Some(sel) = selector.filter(|s| !s.is_empty()) {
        let found = match sel.parse::<usize>() {
            Ok(i) => (i < devices.len()).then_some(i),
            Err(_) => devices
                .iter()
                .position(|(_, d)| d.name.to_lowercase().contains(&sel.to_lowercase())),
        };
        let names: Vec<String> = devices
            .iter()
            .map(|(_, d)| format!("{}: {}", d.index, d.name))
            .collect();
        return found
            .map(|i| picked(i, format!("--device / B2DR_DEVICE {sel:?}")))
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "no Vulkan device matches {sel:?}; available: {}",
                    names.join(", ")
                )
            });
    }
    let ids: Vec<DeviceId> = devices.iter().map(|(_, d)| d.id.clone()).collect();
    let (allowed, why): (Vec<usize>, String) = match scheduler_pin(&ids, &|v| {
        std::env::var(v).ok()
    })? {
        Pin::Device(i, why) => return Ok(picked(i, why)),
        Pin::Unpinned => (
            (0..devices.len()).collect(),
            "default (discrete > integrated > virtual > CPU)".into(),
        ),
        Pin::NoGpu(what) => {
            let others: Vec<usize> = (0..devices.len())
                .filter(|&i| !devices[i].1.id.is_nvidia())
                .collect();
            if others.is_empty() {
                bail!("{what} assigns no GPU to this process and there is no other Vulkan device; give --device or B2DR_DEVICE to use one anyway");
            }
            (
                others,
                format!("{what} (no GPU assigned): the best non-NVIDIA device"),
            )
        }
    };
    let best = allowed
        .into_iter()
        .min_by_key(|&i| (rank_name(&devices[i].1.kind), devices[i].1.index))
        .context("internal: no device left to choose")?;
    Ok(picked(best, why))
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
