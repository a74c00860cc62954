//! Typed Vulkan errors: every failing `vk::Result` of this layer becomes a [`VkError`] (through [`vk_err`]), and
//! allocator failures become [`VkError::OutOfMemory`] (through [`alloc_err`]), so that a caller can tell
//! "out of memory" (retry smaller, free caches) from "device lost" (recreate the context) from the rest:
//! `err.downcast_ref::<VkError>()` on the `anyhow::Error`, or [`VkError::of`], which also looks through
//! contexts added above.
use ash::vk;

/// What went wrong in a Vulkan call, by how a caller can react.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VkError {
    /// Host or device memory ran out (`VK_ERROR_OUT_OF_HOST_MEMORY`, `VK_ERROR_OUT_OF_DEVICE_MEMORY`,
    /// `VK_ERROR_OUT_OF_POOL_MEMORY`, `VK_ERROR_FRAGMENTED_POOL`, `VK_ERROR_FRAGMENTATION`, or the allocator
    /// found no block): the call may succeed with less in use.
    OutOfMemory {
        call: &'static str,
        result: vk::Result,
    },
    /// `VK_ERROR_DEVICE_LOST`: the device and every object made from it are unusable; a new context is needed.
    DeviceLost { call: &'static str },
    /// Any other failure (a bug, a missing feature or extension, ...).
    Other {
        call: &'static str,
        result: vk::Result,
    },
}

impl VkError {
    /// Classifies the result of the Vulkan call `call`.
    pub fn from_result(call: &'static str, result: vk::Result) -> Self {
        match result {
            vk::Result::ERROR_OUT_OF_HOST_MEMORY
            | vk::Result::ERROR_OUT_OF_DEVICE_MEMORY
            | vk::Result::ERROR_OUT_OF_POOL_MEMORY
            | vk::Result::ERROR_FRAGMENTED_POOL
            | vk::Result::ERROR_FRAGMENTATION => VkError::OutOfMemory { call, result },
            vk::Result::ERROR_DEVICE_LOST => VkError::DeviceLost { call },
            _ => VkError::Other { call, result },
        }
    }

    /// The [`VkError`] anywhere in `err`'s chain (contexts added above it included), if there is one.
    pub fn of(err: &anyhow::Error) -> Option<VkError> {
        err.chain()
            .find_map(|e| e.downcast_ref::<VkError>().copied())
    }

    pub fn is_out_of_memory(&self) -> bool {
        matches!(self, VkError::OutOfMemory { .. })
    }

    pub fn is_device_lost(&self) -> bool {
        matches!(self, VkError::DeviceLost { .. })
    }
}

impl std::fmt::Display for VkError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VkError::OutOfMemory { call, result } => {
                write!(f, "{call} failed: out of memory ({result:?})")
            }
            VkError::DeviceLost { call } => {
                write!(f, "{call} failed: device lost (ERROR_DEVICE_LOST)")
            }
            VkError::Other { call, result } => write!(f, "{call} failed: {result:?}"),
        }
    }
}

impl std::error::Error for VkError {}

/// Maps a failing `vk::Result` of the Vulkan call `call` into an `anyhow::Error` holding a [`VkError`].
pub(crate) fn vk_err(call: &'static str) -> impl Fn(vk::Result) -> anyhow::Error {
    move |r| anyhow::Error::new(VkError::from_result(call, r))
}

/// Maps a gpu-allocator failure: running out of memory becomes [`VkError::OutOfMemory`]; anything else stays the
/// allocator's own error.
pub(crate) fn alloc_err(e: gpu_allocator::AllocationError) -> anyhow::Error {
    use gpu_allocator::AllocationError as A;
    match e {
        A::OutOfMemory => anyhow::Error::new(VkError::OutOfMemory {
            call: "gpu-allocator allocate",
            result: vk::Result::ERROR_OUT_OF_DEVICE_MEMORY,
        }),
        other => anyhow::Error::new(other),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_map_by_reaction() {
        for r in [
            vk::Result::ERROR_OUT_OF_HOST_MEMORY,
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY,
            vk::Result::ERROR_OUT_OF_POOL_MEMORY,
            vk::Result::ERROR_FRAGMENTED_POOL,
            vk::Result::ERROR_FRAGMENTATION,
        ] {
            assert!(VkError::from_result("vkX", r).is_out_of_memory(), "{r:?}");
        }
        assert_eq!(
            VkError::from_result("vkQueueSubmit", vk::Result::ERROR_DEVICE_LOST),
            VkError::DeviceLost {
                call: "vkQueueSubmit"
            }
        );
        let o = VkError::from_result("vkCreateDevice", vk::Result::ERROR_EXTENSION_NOT_PRESENT);
        assert_eq!(
            o,
            VkError::Other {
                call: "vkCreateDevice",
                result: vk::Result::ERROR_EXTENSION_NOT_PRESENT
            }
        );
        assert!(!o.is_out_of_memory() && !o.is_device_lost());
    }

    #[test]
    fn downcast_through_context() {
        use anyhow::Context as _;
        let e: anyhow::Error = vk_err("vkQueueSubmit")(vk::Result::ERROR_DEVICE_LOST);
        assert!(e
            .downcast_ref::<VkError>()
            .is_some_and(|v| v.is_device_lost()));
        let e = Err::<(), _>(e).context("recording unet step").unwrap_err();
        assert_eq!(
            VkError::of(&e),
            Some(VkError::DeviceLost {
                call: "vkQueueSubmit"
            })
        );
        assert!(format!("{e:#}").contains("device lost"));
        let oom = alloc_err(gpu_allocator::AllocationError::OutOfMemory);
        assert!(VkError::of(&oom).is_some_and(|v| v.is_out_of_memory()));
        let other = alloc_err(gpu_allocator::AllocationError::InvalidAllocationCreateDesc);
        assert_eq!(VkError::of(&other), None);
    }
}
