//! The Vulkan layer itself: explicit Vulkan control, buffer limits, barriers across a dispatch chain, replay,
//! timestamps, the generated registry.
mod common;
use ash::vk;
use b2dr::kernels::{KernelId, ALL_KERNELS, KERNELS};
use b2dr::ops::elementwise as ew;
use b2dr::tensor::{DType, Tensor};
use b2dr::vk::{Context, ExternalVulkan};
use common::*;

#[test]
fn registry_is_generated_with_variants_and_params() {
    // CPU-only: the registry exists without a device.
    assert_eq!(KERNELS.len(), ALL_KERNELS.len());
    let k = KernelId::by_name("elementwise_f16_scale_add").expect("f16 variant generated");
    let info = k.info();
    assert!(info.f16 && info.variant == "f16" && info.entry == "scale_add");
    assert_eq!(
        info.bindings,
        &[true, true, false],
        "a, b read-only; out read-write"
    );
    assert_eq!(
        info.params_size as usize,
        std::mem::size_of::<b2dr::kernels::params::ScaleAddParams>()
    );
    assert_eq!(info.spirv.len() % 4, 0);
    assert_eq!(
        u32::from_le_bytes(info.spirv[..4].try_into().unwrap()),
        0x0723_0203,
        "SPIR-V magic"
    );
}

#[test]
fn a_dependent_dispatch_chain_is_correctly_ordered() {
    let Some(ctx) = ctx() else { return };
    // x -> silu -> add x -> mul 2 -> scale_add ..., 40 dependent dispatches in one command buffer: wrong or
    // missing barriers show up as stale values.
    let n = 100_003;
    let x0 = uniform(n, 1.0, 1);
    let a = upload(&ctx, &[n], DType::F32, &x0);
    let b = empty(&ctx, &[n], DType::F32);
    let two = upload(&ctx, &[1], DType::F32, &[2.0]);
    let mut want: Vec<f64> = x0.iter().map(|&v| v as f64).collect();
    run(&ctx, |rec| {
        for _ in 0..10 {
            ew::silu(rec, &a, &b)?; // b = silu(a)
            ew::add(rec, &a, &b, &a)?; // a = a + b (in place: out aliases an input element-for-element)
            ew::mul(rec, &a, &two, &a)?; // a = 2 a
            ew::scale_add(rec, 0.5, &a, 0.25, &b, &b)?; // b = 0.5 a + 0.25 b
            ew::scale_add(rec, 1.0, &b, 0.0, &a, &a)?; // a = b
        }
        Ok(())
    });
    for _ in 0..10 {
        for v in want.iter_mut() {
            let s = b2dr::ops::reference::silu(*v);
            let a2 = 2.0 * (*v + s);
            *v = 0.5 * a2 + 0.25 * s;
        }
    }
    let e = nmse(&a.to_f32(&ctx).unwrap(), &want);
    assert!(e < 1e-10, "nmse {e:e}");
    assert_no_validation_errors();
}

#[test]
fn recordings_replay_and_report_timestamps() {
    let Some(ctx) = ctx() else { return };
    let n = 4096;
    let x = upload(&ctx, &[n], DType::F32, &uniform(n, 1.0, 2));
    let acc = upload(&ctx, &[n], DType::F32, &vec![0.0; n]);
    let tmp = empty(&ctx, &[n], DType::F32);
    let mut rec = ctx.recorder_timed(8).unwrap();
    ew::scale_add(&mut rec, 1.0, &acc, 1.0, &x, &tmp).unwrap(); // tmp = acc + x
    ew::scale_add(&mut rec, 1.0, &tmp, 0.0, &x, &acc).unwrap(); // acc = tmp
    let r = rec.finish().unwrap();
    for _ in 0..5 {
        r.submit_wait().unwrap();
    }
    let got = acc.to_f32(&ctx).unwrap();
    let xs = x.to_f32(&ctx).unwrap();
    for (g, v) in got.iter().zip(&xs) {
        assert!(
            (g - 5.0 * v).abs() <= 1e-5 * v.abs().max(1.0),
            "replayed 5 times: {g} vs {}",
            5.0 * v
        );
    }
    let t = r.timings().unwrap();
    if ctx.info().timestamps {
        assert_eq!(t.len(), 2);
        assert!(t.iter().all(|t| t.ms >= 0.0 && t.ms < 10_000.0), "{t:?}");
    }
    assert_no_validation_errors();
}

#[test]
fn buffers_beyond_the_storage_range_are_refused_clearly() {
    let Some(ctx) = ctx() else { return };
    let range = ctx.info().max_storage_buffer_range as usize;
    let n = range / 4 + 1024;
    let e = Tensor::empty(&ctx, &[n], DType::F32, "too-big")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("maxStorageBufferRange") && e.contains("too-big"),
        "{e}"
    );
}

#[test]
fn explicit_vulkan_control_runs_on_a_callers_device() {
    if ctx().is_none() {
        return;
    }
    // The caller creates instance, device and queue with ash and hands them to b2dr.
    // SAFETY: plain Vulkan setup; objects are destroyed at the end after b2dr's context is dropped.
    unsafe {
        let entry = ash::Entry::load().unwrap();
        let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_3);
        let instance = entry
            .create_instance(
                &vk::InstanceCreateInfo::default().application_info(&app),
                None,
            )
            .unwrap();
        let pd = instance.enumerate_physical_devices().unwrap()[0];
        let family = instance
            .get_physical_device_queue_family_properties(pd)
            .iter()
            .position(|q| q.queue_flags.contains(vk::QueueFlags::COMPUTE))
            .unwrap() as u32;
        let prio = [1.0];
        let qci = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(family)
            .queue_priorities(&prio)];
        let device = instance
            .create_device(
                pd,
                &vk::DeviceCreateInfo::default().queue_create_infos(&qci),
                None,
            )
            .unwrap();
        let queue = device.get_device_queue(family, 0);
        {
            let ctx = Context::from_external(ExternalVulkan {
                entry: entry.clone(),
                instance: instance.clone(),
                physical_device: pd,
                device: device.clone(),
                queue,
                queue_family: family,
                f16_enabled: false,
            })
            .unwrap();
            assert!(!ctx.info().f16, "f16 was not enabled by the caller");
            let x = upload(&ctx, &[3], DType::F32, &[1.0, -2.0, 0.5]);
            let y = empty(&ctx, &[3], DType::F32);
            run(&ctx, |rec| ew::scale_add(rec, 2.0, &x, 1.0, &x, &y));
            assert_eq!(y.to_f32(&ctx).unwrap(), vec![3.0, -6.0, 1.5]);
            // An f16 kernel is refused with a clear error on this device.
            let h = Tensor::empty(&ctx, &[3], DType::F16, "h").unwrap();
            let mut rec = ctx.recorder().unwrap();
            let e = ew::silu(&mut rec, &h, &h).unwrap_err().to_string();
            assert!(e.contains("f16") && e.contains("lacks"), "{e}");
        }
        // b2dr destroyed only its own objects: the caller's device still works and is destroyed by the caller.
        device.device_wait_idle().unwrap();
        device.destroy_device(None);
        instance.destroy_instance(None);
    }
}

/// The driver's identity (VkPhysicalDeviceDriverProperties) and how it evaluates f16 (`cast.wgsl`'s
/// `f16_probe`): the probe gives one of the outcomes it knows (anything else is an error), on every driver that
/// reports f16 support.
#[test]
fn driver_info_and_f16_arithmetic_probe() {
    let Some(ctx) = ctx() else { return };
    let info = ctx.info();
    assert!(
        !info.driver_info.is_empty(),
        "driverName / driverInfo empty"
    );
    let r = b2dr::ops::cast::f16_probe(&ctx).expect("f16 probe");
    assert_eq!(r.is_some(), info.f16);
    eprintln!("driver {}: {r:?}", info.driver_info);
    assert_no_validation_errors();
}
