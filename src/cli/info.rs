//! `b2dr info`: Vulkan devices, the chosen one and the features b2dr uses.
use anyhow::Result;
use b2dr::kernels::KERNELS;
use b2dr::vk::{Context, ContextOptions};

pub fn run(device: Option<String>) -> Result<()> {
    let devices = Context::list_devices()?;
    println!("Vulkan devices:");
    for d in &devices {
        println!(
            "  [{}] {} ({}, Vulkan {})",
            d.index, d.name, d.kind, d.api_version
        );
        let pci =
            d.id.pci
                .map(|[dom, bus, dev, f]| format!(", PCI {dom:04x}:{bus:02x}:{dev:02x}.{f:x}"))
                .unwrap_or_default();
        println!("      uuid {}{pci}", d.id.uuid_string());
        if !d.driver_info.is_empty() {
            println!("      driver {}", d.driver_info);
        }
    }
    for v in [
        "CUDA_VISIBLE_DEVICES",
        "NVIDIA_VISIBLE_DEVICES",
        "B2DR_DEVICE",
    ] {
        if let Ok(x) = std::env::var(v) {
            println!("{v}={x}");
        }
    }
    let ctx = Context::new(&ContextOptions {
        device,
        profile: false,
        ..Default::default()
    })?;
    let i = ctx.info();
    let yes = |b: bool| if b { "yes" } else { "no" };
    println!("chosen: [{}] {} ({})", i.index, i.name, i.kind);
    println!("  uuid:                       {}", i.id.uuid_string());
    println!("  driver:                     {}", i.driver_info);
    println!("  chosen by:                  {}", i.selected_by);
    println!("  f16 storage + arithmetic:   {}", yes(i.f16));
    // the probe's own failure is reported, not fatal: `info` is what one runs to look at a misbehaving driver
    match b2dr::ops::cast::f16_probe(&ctx) {
        Ok(Some(f)) => {
            let ops = if f.rounds_per_op {
                "rounds every operation to f16 (IEEE half arithmetic)"
            } else {
                "evaluated in f32, rounded to f16 only when stored"
            };
            let trip = if f.round_trip_kept {
                "rounds to f16"
            } else {
                "dropped by the compiler (gives x back)"
            };
            println!("  f16 arithmetic:             {ops}");
            println!("  f32(f16(x)) round trip:     {trip}");
        }
        Ok(None) => {}
        Err(e) => println!("  f16 probe:                  failed: {e:#}"),
    }
    println!(
        "  subgroups (size {}):         {}",
        i.subgroup_size,
        yes(i.subgroup)
    );
    println!(
        "  cooperative matrix:         {}",
        yes(i.cooperative_matrix)
    );
    println!(
        "  max storage buffer range:   {} MiB",
        i.max_storage_buffer_range >> 20
    );
    println!(
        "  shared memory per group:    {} KiB",
        i.max_shared_memory >> 10
    );
    println!("  timestamps:                 {}", yes(i.timestamps));
    println!(
        "  validation layer:           {}",
        if ctx.validation_enabled() {
            "on"
        } else {
            "off (B2DR_VALIDATION=1 enables it)"
        }
    );
    let runnable = b2dr::kernels::ALL_KERNELS
        .iter()
        .filter(|k| ctx.supports(**k))
        .count();
    println!(
        "kernels: {} compiled, {} runnable on this device",
        KERNELS.len(),
        runnable
    );
    Ok(())
}
