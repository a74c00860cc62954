//! Compute pipelines, created lazily from the generated registry and cached per kernel id.
use std::sync::Arc;

use anyhow::{bail, Result};
use ash::vk;

use super::{vk_err, Context};
use crate::kernels::{KernelId, KernelInfo, KERNELS};

pub(crate) struct Pipeline {
    pub layout: vk::PipelineLayout,
    pub set_layout: vk::DescriptorSetLayout,
    pub pipeline: vk::Pipeline,
    pub module: vk::ShaderModule,
    pub info: &'static KernelInfo,
}

impl Pipeline {
    /// # Safety
    /// No command buffer using the pipeline may be pending.
    pub unsafe fn destroy(self, d: &ash::Device) {
        // SAFETY: caller contract.
        unsafe {
            d.destroy_pipeline(self.pipeline, None);
            d.destroy_pipeline_layout(self.layout, None);
            d.destroy_descriptor_set_layout(self.set_layout, None);
            d.destroy_shader_module(self.module, None);
        }
    }
}

/// Storage buffer, or storage image for a texel-view binding.
pub(crate) fn descriptor_type(info: &KernelInfo, binding: usize) -> vk::DescriptorType {
    if info.images[binding] {
        vk::DescriptorType::STORAGE_IMAGE
    } else {
        vk::DescriptorType::STORAGE_BUFFER
    }
}

impl Context {
    /// Whether the device can run a kernel (f16 / subgroup / cooperative-matrix requirements).
    pub fn supports(&self, id: KernelId) -> bool {
        let k = &KERNELS[id as usize];
        let i = &self.inner.info;
        (!k.f16 || i.f16)
            && (!k.subgroup || i.subgroup)
            && (!k.coop_matrix || i.cooperative_matrix)
            && (!k.images.contains(&true) || (i.linear_images && i.is_cpu()))
    }

    pub(crate) fn pipeline(&self, id: KernelId) -> Result<Arc<Pipeline>> {
        let mut cache = self.inner.pipelines.lock().expect("pipeline cache lock");
        if let Some(p) = cache.get(&id) {
            return Ok(p.clone());
        }
        let info = &KERNELS[id as usize];
        if !self.supports(id) {
            bail!(
                "kernel {} needs {}{}{} which device {:?} lacks",
                info.name,
                if info.f16 { "f16 " } else { "" },
                if info.subgroup { "subgroups " } else { "" },
                if info.coop_matrix {
                    "cooperative matrices"
                } else {
                    ""
                },
                self.inner.info.name
            );
        }
        let p = Arc::new(self.create_pipeline(info)?);
        cache.insert(id, p.clone());
        Ok(p)
    }

    fn create_pipeline(&self, info: &'static KernelInfo) -> Result<Pipeline> {
        let d = &self.inner.device;
        let code: Vec<u32> = info
            .spirv
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let bindings: Vec<_> = (0..info.bindings.len() as u32)
            .map(|b| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(b)
                    .descriptor_type(descriptor_type(info, b as usize))
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE)
            })
            .collect();
        // SAFETY: each create call gets a valid create info; objects are destroyed in Pipeline::destroy.
        unsafe {
            let module = d
                .create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&code), None)
                .map_err(vk_err("vkCreateShaderModule"))?;
            let set_layout = d
                .create_descriptor_set_layout(
                    &vk::DescriptorSetLayoutCreateInfo::default().bindings(&bindings),
                    None,
                )
                .map_err(vk_err("vkCreateDescriptorSetLayout"))?;
            let ranges = [vk::PushConstantRange::default()
                .stage_flags(vk::ShaderStageFlags::COMPUTE)
                .offset(0)
                .size(info.params_size)];
            let layouts = [set_layout];
            let mut lci = vk::PipelineLayoutCreateInfo::default().set_layouts(&layouts);
            if info.params_size > 0 {
                lci = lci.push_constant_ranges(&ranges);
            }
            let layout = d
                .create_pipeline_layout(&lci, None)
                .map_err(vk_err("vkCreatePipelineLayout"))?;
            let entry = std::ffi::CString::new(info.entry)?;
            let stage = vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::COMPUTE)
                .module(module)
                .name(&entry);
            let ci = [vk::ComputePipelineCreateInfo::default()
                .stage(stage)
                .layout(layout)];
            let pipeline = d
                .create_compute_pipelines(vk::PipelineCache::null(), &ci, None)
                .map_err(|(_, r)| {
                    anyhow::anyhow!("vkCreateComputePipelines({}) failed: {r:?}", info.name)
                })?[0];
            self.set_name(pipeline, info.name);
            self.set_name(module, info.name);
            Ok(Pipeline {
                layout,
                set_layout,
                pipeline,
                module,
                info,
            })
        }
    }
}
