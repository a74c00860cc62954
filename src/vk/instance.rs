//! Vulkan instance creation and the validation-layer message sink.
use std::ffi::{c_void, CStr};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use anyhow::{Context as _, Result};
use ash::vk;

use super::vk_err;

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// Validation errors seen by this process (all contexts). Tests assert this stays zero.
static VALIDATION_ERRORS: AtomicUsize = AtomicUsize::new(0);
static VALIDATION_LOG: Mutex<Vec<String>> = Mutex::new(Vec::new());

/// Number of validation-layer errors reported so far in this process, and the first messages.
pub fn validation_errors() -> (usize, Vec<String>) {
    let log = VALIDATION_LOG.lock().map(|l| l.clone()).unwrap_or_default();
    (VALIDATION_ERRORS.load(Ordering::SeqCst), log)
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    ty: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    _user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: the loader passes a valid callback-data pointer whose message is a NUL-terminated string.
    let msg = unsafe { data.as_ref().and_then(|d| d.message_as_c_str()) }
        .map(|m| m.to_string_lossy().into_owned())
        .unwrap_or_default();
    if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR) {
        VALIDATION_ERRORS.fetch_add(1, Ordering::SeqCst);
        if let Ok(mut l) = VALIDATION_LOG.lock() {
            if l.len() < 32 {
                l.push(msg.clone());
            }
        }
        eprintln!("[vulkan validation error] {msg}");
    } else if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::WARNING)
        && ty.contains(vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION)
    {
        eprintln!("[vulkan validation warning] {msg}");
    }
    vk::FALSE
}

pub(super) struct InstanceParts {
    pub entry: ash::Entry,
    pub instance: ash::Instance,
    pub debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    pub validation: bool,
}

/// Whether validation was asked for: `B2DR_VALIDATION=1` (or `true`).
pub fn validation_requested() -> bool {
    matches!(
        std::env::var("B2DR_VALIDATION").as_deref(),
        Ok("1") | Ok("true") | Ok("on")
    )
}

pub(super) fn create_instance(validation: bool) -> Result<InstanceParts> {
    // SAFETY: loading the system Vulkan loader; failure is reported as an error.
    let entry = unsafe { ash::Entry::load() }
        .context("could not load the Vulkan loader (libvulkan.so.1); on Debian: apt-get install libvulkan1 mesa-vulkan-drivers")?;
    // SAFETY: plain queries on a loaded entry.
    let layers = unsafe { entry.enumerate_instance_layer_properties() }
        .map_err(vk_err("vkEnumerateInstanceLayerProperties"))?;
    let has_layer = layers
        .iter()
        .any(|l| l.layer_name_as_c_str() == Ok(VALIDATION_LAYER));
    let validation = if validation && !has_layer {
        eprintln!("b2dr: validation requested but VK_LAYER_KHRONOS_validation is not installed (apt-get install vulkan-validationlayers); running without it");
        false
    } else {
        validation
    };
    let app = vk::ApplicationInfo::default()
        .application_name(c"b2dr")
        .engine_name(c"b2dr")
        .api_version(vk::API_VERSION_1_3);
    let layer_names = if validation {
        vec![VALIDATION_LAYER.as_ptr()]
    } else {
        vec![]
    };
    let ext_names = if validation {
        vec![ash::ext::debug_utils::NAME.as_ptr()]
    } else {
        vec![]
    };
    let ci = vk::InstanceCreateInfo::default()
        .application_info(&app)
        .enabled_layer_names(&layer_names)
        .enabled_extension_names(&ext_names);
    // SAFETY: create info and the strings it points to outlive the call.
    let instance =
        unsafe { entry.create_instance(&ci, None) }.map_err(vk_err("vkCreateInstance"))?;
    let debug = if validation {
        let du = ash::ext::debug_utils::Instance::new(&entry, &instance);
        let mci = vk::DebugUtilsMessengerCreateInfoEXT::default()
            .message_severity(
                vk::DebugUtilsMessageSeverityFlagsEXT::ERROR
                    | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING,
            )
            .message_type(
                vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                    | vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                    | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
            )
            .pfn_user_callback(Some(debug_callback));
        // SAFETY: instance was created with the debug-utils extension enabled.
        let m = unsafe { du.create_debug_utils_messenger(&mci, None) }
            .map_err(vk_err("vkCreateDebugUtilsMessengerEXT"))?;
        Some((du, m))
    } else {
        None
    };
    Ok(InstanceParts {
        entry,
        instance,
        debug,
        validation,
    })
}
