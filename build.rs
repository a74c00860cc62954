//! Compiles every kernel in `kernels/*.wgsl` (and `kernels/<file>/` folders) through naga (WGSL -> validated IR
//! -> SPIR-V 1.3) and generates
//! the kernel registry `$OUT_DIR/kernels.rs` (ids, SPIR-V, bindings, workgroup sizes, parameter structs).
//!
//! Kernel file conventions:
//! - Variants come from one source. Header lines `//! variant <name> [<entry>, ...]: <wgsl snippet>` at the
//!   top of a file declare them; for variant X the line of X is replaced *in place* by its snippet (so
//!   file:line in errors stays exact) and the other header lines stay comments. A file without header lines
//!   has one variant named after the file alone. Snippets hold `enable f16;`, `alias` and `const`
//!   declarations (dtype, tile sizes). The optional `[entries]` list names the entry points compiled for that
//!   variant (default: all).
//! - A variant's name states its axes, `<dtype>[t|p|chk][_d<N>|_w<N>][r<N>]`: dtype `f32`/`f16`; `t` reads
//!   some bindings through texel views, `p` reads f16 as packed pairs, `chk` writes an f16 overflow flag;
//!   `d`/`w` the head dim (columns), `r` rows per lane. They become the typed `kernels::Variant` of every
//!   entry, and per file a `kernels::lookup::<file>(<File>Entry, Variant) -> Option<KernelId>` const fn: the
//!   only way launchers name a variant. A texel (`t`) variant's entry that reads no binding through a texel
//!   view is not compiled (nothing would pick it); two entries with the same file, entry and axes fail the
//!   build.
//! - `kernels/common.wgsl` is appended to every kernel (shared helpers); errors in it are reported there.
//! - A folder `kernels/<file>/` is one kernel file split by algorithm: its `*.wgsl` files concatenated in name
//!   order (`00_common.wgsl` first, holding the variant header lines), compiled and looked up as `<file>`;
//!   errors name the part file and its line.
//! - Every `@compute` entry point becomes a registry entry `<file>_<variant>[_<entry>]` (entry `main` omitted).
//! - Storage buffers are `@group(0) @binding(0..n)` (contiguous); a binding may also be a
//!   `texture_storage_2d<rgba32float, read>`: a texel view of the buffer bound there (src/vk/image.rs).
//!   Parameters are one `var<immediate>` struct of 4-byte scalars; the matching `#[repr(C)]` Rust struct is
//!   generated here with a compile-time size assert.
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use naga::back::spv;
use naga::valid::{Capabilities, ShaderStages, SubgroupOperationSet, ValidationFlags, Validator};

struct Variant {
    name: String,
    snippet: String,
    line: usize,
    /// Entry points compiled for this variant (None: all).
    entries: Option<Vec<String>>,
    axes: Axes,
}

/// The axes a variant's name states (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
struct Axes {
    /// 0 none, 32 f32, 16 f16
    dtype: u32,
    texel: bool,
    packed: bool,
    checked: bool,
    cols: u32,
    rows: u32,
}

impl Axes {
    fn parse(name: &str) -> Option<Axes> {
        if name.is_empty() {
            return Some(Axes {
                rows: 1,
                ..Axes::default()
            });
        }
        let (head, tail) = name.split_once('_').unwrap_or((name, ""));
        let (dtype, flag) = if let Some(f) = head.strip_prefix("f32") {
            (32, f)
        } else {
            (16, head.strip_prefix("f16")?)
        };
        let mut a = Axes {
            dtype,
            rows: 1,
            ..Axes::default()
        };
        match flag {
            "" => {}
            "t" => a.texel = true,
            "p" => a.packed = true,
            "chk" => a.checked = true,
            _ => return None,
        }
        if !tail.is_empty() {
            let t = tail.strip_prefix('d').or_else(|| tail.strip_prefix('w'))?;
            let (cols, rows) = t.split_once('r').unwrap_or((t, "1"));
            a.cols = cols.parse().ok()?;
            a.rows = rows.parse().ok()?;
        }
        Some(a)
    }

    fn rust(&self) -> String {
        let dtype = match self.dtype {
            32 => "Some(crate::tensor::DType::F32)",
            16 => "Some(crate::tensor::DType::F16)",
            _ => "None",
        };
        format!(
            "Variant {{ dtype: {dtype}, texel: {}, packed_f16: {}, overflow_flag: {}, cols: {}, rows: {} }}",
            self.texel, self.packed, self.checked, self.cols, self.rows
        )
    }

    fn pattern(&self) -> String {
        self.rust()
    }
}

struct Entry {
    id: String,
    file: String,
    variant: String,
    axes: Axes,
    entry: String,
    spv_file: PathBuf,
    bindings: Vec<bool>, // read_only per binding
    images: Vec<bool>,   // storage-image (texel view) binding
    workgroup: [u32; 3],
    params: Option<String>,
    params_size: u32,
    f16: bool,
    subgroup: bool,
    coop: bool,
}

fn main() {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").unwrap());
    let out = PathBuf::from(std::env::var("OUT_DIR").unwrap());
    let kdir = root.join("kernels");
    println!("cargo:rerun-if-changed=kernels");
    let common_path = kdir.join("common.wgsl");
    let common = std::fs::read_to_string(&common_path).unwrap_or_default();

    let mut files: Vec<PathBuf> = std::fs::read_dir(&kdir)
        .map(|rd| rd.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    files.retain(|p| {
        (p.extension().is_some_and(|e| e == "wgsl") && p.file_name().unwrap() != "common.wgsl")
            || p.is_dir()
    });
    files.sort();

    let mut entries: Vec<Entry> = Vec::new();
    let mut structs: BTreeMap<String, (String, u32)> = BTreeMap::new(); // name -> (rust code, size)
    let mut failed = false;
    for path in &files {
        println!("cargo:rerun-if-changed={}", path.display());
        let stem = path.file_stem().unwrap().to_string_lossy().to_string();
        let (src, mut segments) = read_kernel(path);
        let lines: Vec<&str> = src.lines().collect();
        segments.push((common_path.clone(), lines.len()));
        let variants = parse_variants(&stem, &lines);
        for v in &variants {
            let mut text = String::new();
            for (i, l) in lines.iter().enumerate() {
                if v.line == i + 1 {
                    text.push_str(&v.snippet);
                } else {
                    text.push_str(l);
                }
                text.push('\n');
            }
            text.push_str(&common);
            match compile(&text, path, &segments) {
                Ok((module, info)) => {
                    let vname = if v.name.is_empty() {
                        stem.clone()
                    } else {
                        format!("{stem}_{}", v.name)
                    };
                    collect_entries(
                        &module,
                        &info,
                        &out,
                        &stem,
                        v,
                        &vname,
                        &text,
                        &mut entries,
                        &mut structs,
                    )
                    .unwrap_or_else(|e| {
                        println!("cargo:warning={}: {e}", path.display());
                        failed = true;
                    });
                }
                Err(msg) => {
                    for l in msg.lines() {
                        println!("cargo:warning={l}");
                    }
                    eprintln!("{msg}");
                    failed = true;
                }
            }
        }
    }
    if failed {
        panic!("kernel compilation failed (see the messages above: file:line)");
    }
    std::fs::write(out.join("kernels.rs"), generate(&entries, &structs)).unwrap();
}

fn parse_variants(stem: &str, lines: &[&str]) -> Vec<Variant> {
    let mut v = Vec::new();
    for (i, l) in lines.iter().enumerate() {
        let t = l.trim();
        if let Some(rest) = t.strip_prefix("//! variant ") {
            let (head, snippet) = rest
                .split_once(':')
                .unwrap_or_else(|| panic!("{stem}.wgsl:{}: bad variant line", i + 1));
            let (name, entries) = match head.split_once('[') {
                Some((n, list)) => {
                    let list = list
                        .trim()
                        .strip_suffix(']')
                        .unwrap_or_else(|| panic!("{stem}.wgsl:{}: unclosed entry list", i + 1));
                    let e = list.split(',').map(|e| e.trim().to_string()).collect();
                    (n.trim(), Some(e))
                }
                None => (head.trim(), None),
            };
            let axes = Axes::parse(name).unwrap_or_else(|| {
                panic!(
                    "{stem}.wgsl:{}: variant name {name:?} does not read as <dtype>[t|p|chk][_d<N>|_w<N>][r<N>]",
                    i + 1
                )
            });
            v.push(Variant {
                name: name.to_string(),
                snippet: snippet.trim().to_string(),
                line: i + 1,
                entries,
                axes,
            });
        } else if !t.starts_with("//") && !t.is_empty() {
            break;
        }
    }
    if v.is_empty() {
        v.push(Variant {
            name: String::new(),
            snippet: String::new(),
            line: 0,
            entries: None,
            axes: Axes::parse("").unwrap(),
        });
    }
    v
}

type Compiled = (naga::Module, naga::valid::ModuleInfo);

/// The parts of a compiled text: (file, lines of the text before it), in order.
type Segments = Vec<(PathBuf, usize)>;

/// A kernel's source: a `.wgsl` file, or a folder's `*.wgsl` files concatenated in name order; with the
/// segments that map its lines back to the files.
fn read_kernel(path: &Path) -> (String, Segments) {
    if !path.is_dir() {
        return (
            std::fs::read_to_string(path).unwrap(),
            vec![(path.to_path_buf(), 0)],
        );
    }
    let mut parts: Vec<PathBuf> = std::fs::read_dir(path)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "wgsl"))
        .collect();
    parts.sort();
    assert!(
        !parts.is_empty(),
        "{}: a kernel folder without .wgsl files",
        path.display()
    );
    let (mut text, mut segments) = (String::new(), vec![]);
    for p in parts {
        println!("cargo:rerun-if-changed={}", p.display());
        segments.push((p.clone(), text.lines().count()));
        let t = std::fs::read_to_string(&p).unwrap();
        text.push_str(&t);
        if !t.ends_with('\n') {
            text.push('\n');
        }
    }
    (text, segments)
}

/// Maps a line of the concatenated text back to (file, line).
fn locate(line: usize, segments: &Segments) -> String {
    let (file, before) = segments
        .iter()
        .rev()
        .find(|(_, before)| line > *before)
        .unwrap_or(&segments[0]);
    format!("{}:{}", file.display(), line - before)
}

fn compile(text: &str, path: &Path, segments: &Segments) -> Result<Compiled, String> {
    let pname = path.display().to_string();
    let module = naga::front::wgsl::parse_str(text).map_err(|e| {
        let loc = e
            .location(text)
            .map(|l| locate(l.line_number as usize, segments));
        format!(
            "{}: error: {}\n{}",
            loc.unwrap_or_default(),
            e.message(),
            e.emit_to_string_with_path(text, &pname)
        )
    })?;
    let caps = Capabilities::IMMEDIATES
        | Capabilities::SHADER_FLOAT16
        | Capabilities::SUBGROUP
        | Capabilities::COOPERATIVE_MATRIX;
    let info = Validator::new(ValidationFlags::all(), caps)
        .subgroup_stages(ShaderStages::COMPUTE)
        .subgroup_operations(SubgroupOperationSet::all())
        .validate(&module)
        .map_err(|e| {
            let loc = e
                .spans()
                .next()
                .map(|(s, _)| locate(s.location(text).line_number as usize, segments));
            format!(
                "{}: error: {}\n{}",
                loc.unwrap_or_default(),
                e,
                e.emit_to_string_with_path(text, &pname)
            )
        })?;
    Ok((module, info))
}

#[allow(clippy::too_many_arguments)]
fn collect_entries(
    module: &naga::Module,
    info: &naga::valid::ModuleInfo,
    out: &Path,
    file: &str,
    variant: &Variant,
    vname: &str,
    text: &str,
    entries: &mut Vec<Entry>,
    structs: &mut BTreeMap<String, (String, u32)>,
) -> Result<(), String> {
    for e in variant.entries.iter().flatten() {
        if !module.entry_points.iter().any(|ep| &ep.name == e) {
            return Err(format!(
                "variant {vname}: entry list names {e:?}, which the file lacks"
            ));
        }
    }
    for (ei, ep) in module.entry_points.iter().enumerate() {
        if ep.stage != naga::ShaderStage::Compute {
            continue;
        }
        if variant
            .entries
            .as_ref()
            .is_some_and(|l| !l.contains(&ep.name))
        {
            continue;
        }
        let fi = info.get_entry_point(ei);
        let mut bindings: BTreeMap<u32, bool> = BTreeMap::new();
        let mut images: BTreeMap<u32, bool> = BTreeMap::new();
        let mut params = None;
        let mut params_size = 0;
        for (h, var) in module.global_variables.iter() {
            if fi[h].is_empty() {
                continue;
            }
            match var.space {
                naga::AddressSpace::Storage { access } => {
                    let b = var
                        .binding
                        .as_ref()
                        .ok_or("storage buffer without binding")?;
                    if b.group != 0 {
                        return Err(format!("{}: bindings must be in group 0", ep.name));
                    }
                    bindings.insert(b.binding, !access.contains(naga::StorageAccess::STORE));
                    images.insert(b.binding, false);
                }
                naga::AddressSpace::Handle => {
                    // only read-only rgba32f storage images: texel views of buffers (src/vk/image.rs)
                    let b = var.binding.as_ref().ok_or("image without binding")?;
                    let ok = matches!(
                        module.types[var.ty].inner,
                        naga::TypeInner::Image {
                            dim: naga::ImageDimension::D2,
                            arrayed: false,
                            class: naga::ImageClass::Storage {
                                format: naga::StorageFormat::Rgba32Float,
                                access,
                            },
                        } if access == naga::StorageAccess::LOAD
                    );
                    if !ok || b.group != 0 {
                        return Err(format!(
                            "{}: binding {} must be a group-0 texture_storage_2d<rgba32float, read>",
                            ep.name, b.binding
                        ));
                    }
                    bindings.insert(b.binding, true);
                    images.insert(b.binding, true);
                }
                naga::AddressSpace::Immediate => {
                    let ty = &module.types[var.ty];
                    let name = ty.name.clone().ok_or("immediate struct needs a name")?;
                    let (code, size) = rust_struct(module, var.ty, &name)?;
                    if let Some((prev, _)) = structs.get(&name) {
                        if *prev != code {
                            return Err(format!(
                                "struct {name} defined twice with different layouts"
                            ));
                        }
                    }
                    structs.insert(name.clone(), (code, size));
                    params = Some(name);
                    params_size = size;
                }
                naga::AddressSpace::WorkGroup
                | naga::AddressSpace::Private
                | naga::AddressSpace::Function => {}
                other => return Err(format!("{}: unsupported address space {other:?}", ep.name)),
            }
        }
        if variant.axes.texel && !images.values().any(|&i| i) {
            // the texel variant of an entry that reads nothing through a texel view: never picked
            continue;
        }
        let n = bindings.len() as u32;
        if bindings.keys().copied().ne(0..n) {
            return Err(format!(
                "{}: bindings must be contiguous from 0, got {:?}",
                ep.name,
                bindings.keys()
            ));
        }
        // One SPIR-V module per entry point keeps each pipeline's module minimal.
        let opts_ep = spv::PipelineOptions {
            shader_stage: naga::ShaderStage::Compute,
            entry_point: ep.name.clone(),
        };
        let opts = spv::Options {
            lang_version: (1, 3),
            flags: spv::WriterFlags::empty(),
            // Vulkan: group/binding map directly to descriptor set/binding.
            fake_missing_bindings: true,
            zero_initialize_workgroup_memory: spv::ZeroInitializeWorkgroupMemoryMode::None,
            force_loop_bounding: false,
            use_storage_input_output_16: false,
            emit_int_div_checks: false,
            bounds_check_policies: naga::proc::BoundsCheckPolicies {
                index: naga::proc::BoundsCheckPolicy::Unchecked,
                buffer: naga::proc::BoundsCheckPolicy::Unchecked,
                image_load: naga::proc::BoundsCheckPolicy::Unchecked,
                binding_array: naga::proc::BoundsCheckPolicy::Unchecked,
            },
            ..Default::default()
        };
        let words =
            spv::write_vec(module, info, &opts, Some(&opts_ep)).map_err(|e| e.to_string())?;
        // Feature flags from code lines only: header lines of other variants stay in the text as comments.
        let code: String = text
            .lines()
            .filter(|l| !l.trim_start().starts_with("//"))
            .collect::<Vec<_>>()
            .join("\n");
        let id = if ep.name == "main" {
            vname.to_string()
        } else {
            format!("{vname}_{}", ep.name)
        };
        let spv_file = out.join(format!("{id}.spv"));
        std::fs::write(&spv_file, bytemuck_words(&words)).unwrap();
        entries.push(Entry {
            id,
            file: file.to_string(),
            variant: variant.name.clone(),
            axes: variant.axes,
            entry: ep.name.clone(),
            spv_file,
            bindings: bindings.values().copied().collect(),
            images: images.values().copied().collect(),
            workgroup: ep.workgroup_size,
            params,
            params_size,
            f16: code.contains("enable f16;"),
            subgroup: code.contains("subgroup"),
            coop: code.contains("wgpu_cooperative_matrix"),
        });
    }
    Ok(())
}

fn bytemuck_words(w: &[u32]) -> Vec<u8> {
    w.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Generates the `#[repr(C)]` mirror of a WGSL parameter struct (4-byte scalars only; gaps become padding).
fn rust_struct(
    module: &naga::Module,
    ty: naga::Handle<naga::Type>,
    name: &str,
) -> Result<(String, u32), String> {
    let naga::TypeInner::Struct { members, span } = &module.types[ty].inner else {
        return Err(format!("{name}: immediate must be a struct"));
    };
    let mut code = format!(
        "/// Parameters of the WGSL struct `{name}` (generated by build.rs).\n#[repr(C)]\n#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]\npub struct {name} {{\n"
    );
    let mut off = 0u32;
    let mut pad = 0;
    let mut asserts = String::new();
    for m in members {
        let mname = m.name.clone().ok_or("unnamed member")?;
        let rty = match &module.types[m.ty].inner {
            naga::TypeInner::Scalar(s) if s.width == 4 => match s.kind {
                naga::ScalarKind::Uint => "u32",
                naga::ScalarKind::Sint => "i32",
                naga::ScalarKind::Float => "f32",
                _ => return Err(format!("{name}.{mname}: unsupported scalar")),
            },
            _ => {
                return Err(format!(
                    "{name}.{mname}: parameter members must be 4-byte scalars"
                ))
            }
        };
        while off < m.offset {
            let _ = writeln!(code, "    pub _pad{pad}: u32,");
            pad += 1;
            off += 4;
        }
        let _ = writeln!(code, "    pub {mname}: {rty},");
        let _ = writeln!(
            asserts,
            "const _: () = assert!(core::mem::offset_of!({name}, {mname}) == {});",
            m.offset
        );
        off = m.offset + 4;
    }
    while off < *span {
        let _ = writeln!(code, "    pub _pad{pad}: u32,");
        pad += 1;
        off += 4;
    }
    code.push_str("}\n");
    let _ = writeln!(
        code,
        "const _: () = assert!(core::mem::size_of::<{name}>() == {span});"
    );
    code.push_str(&asserts);
    Ok((code, *span))
}

fn camel(s: &str) -> String {
    s.split('_')
        .map(|p| {
            let mut c = p.chars();
            c.next()
                .map(|f| f.to_uppercase().collect::<String>() + c.as_str())
                .unwrap_or_default()
        })
        .collect()
}

fn generate(entries: &[Entry], structs: &BTreeMap<String, (String, u32)>) -> String {
    let mut s = String::from("// @generated by build.rs from kernels/*.wgsl. Do not edit.\n\n");
    s.push_str("/// Every compiled kernel entry point (`<file>_<variant>[_<entry>]`).\n");
    s.push_str("#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]\n#[repr(u32)]\npub enum KernelId {\n");
    for e in entries {
        let _ = writeln!(s, "    {},", camel(&e.id));
    }
    s.push_str("}\n\n");
    s.push_str(
        "/// Every kernel id, in registry order.\npub static ALL_KERNELS: &[KernelId] = &[\n",
    );
    for e in entries {
        let _ = writeln!(s, "    KernelId::{},", camel(&e.id));
    }
    s.push_str("];\n\n");
    s.push_str("/// All kernels, indexed by `KernelId as usize`.\npub static KERNELS: &[KernelInfo] = &[\n");
    for e in entries {
        let _ = writeln!(
            s,
            "    KernelInfo {{ name: {:?}, file: {:?}, variant: {:?}, axes: {}, entry: {:?}, spirv: include_bytes!({:?}), \
             bindings: &{:?}, images: &{:?}, workgroup_size: {:?}, params: {:?}, params_size: {}, f16: {}, subgroup: {}, coop_matrix: {} }},",
            e.id,
            format!("kernels/{}.wgsl", e.file),
            e.variant,
            e.axes.rust(),
            e.entry,
            e.spv_file.display().to_string(),
            e.bindings,
            e.images,
            e.workgroup,
            e.params,
            e.params_size,
            e.f16,
            e.subgroup,
            e.coop
        );
    }
    s.push_str("];\n\n");
    s.push_str(&lookups(entries));
    s.push_str("\npub mod params {\n    //! Kernel parameter structs mirrored from WGSL (generated; sizes/offsets asserted at compile time).\n");
    for (code, _) in structs.values() {
        for l in code.lines() {
            let _ = writeln!(s, "    {l}");
        }
    }
    s.push_str("}\n");
    s
}

/// Per kernel file, an enum of its entry points and a const fn from (entry, variant axes) to the kernel id;
/// and `KernelId::with_variant` (the same entry of the same file in other axes). Duplicate keys fail.
fn lookups(entries: &[Entry]) -> String {
    let mut files: BTreeMap<&str, BTreeMap<&str, Vec<&Entry>>> = BTreeMap::new();
    for e in entries {
        files
            .entry(e.file.as_str())
            .or_default()
            .entry(e.entry.as_str())
            .or_default()
            .push(e);
    }
    let mut s = String::from(
        "/// Typed lookups of kernel variants (generated by build.rs from the variant names' axes).\npub mod lookup {\n    use super::{KernelId, Variant};\n",
    );
    let mut with = String::from(
        "impl KernelId {\n    /// The same entry point of the same kernel file in the variant with axes `v`, if it is compiled.\n    pub const fn with_variant(self, v: Variant) -> Option<KernelId> {\n        match self {\n",
    );
    for (file, eps) in &files {
        let ty = format!("{}Entry", camel(file));
        let _ = writeln!(
            s,
            "\n    /// Entry points of `kernels/{file}.wgsl`.\n    #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]\n    pub enum {ty} {{"
        );
        for ep in eps.keys() {
            let _ = writeln!(s, "        {},", camel(ep));
        }
        let _ = writeln!(
            s,
            "    }}\n\n    /// The kernel of `kernels/{file}.wgsl` entry `entry` in the variant with axes `v`, if it is compiled.\n    pub const fn {file}(entry: {ty}, v: Variant) -> Option<KernelId> {{\n        match (entry, v) {{"
        );
        for (ep, es) in eps {
            let mut seen = std::collections::BTreeSet::new();
            for e in es {
                assert!(
                    seen.insert(e.axes),
                    "kernels/{file}.wgsl: entry {ep} has two variants with the axes {:?}",
                    e.axes
                );
                let _ = writeln!(
                    s,
                    "            ({ty}::{}, {}) => Some(KernelId::{}),",
                    camel(ep),
                    e.axes.pattern(),
                    camel(&e.id)
                );
                let _ = writeln!(
                    with,
                    "            KernelId::{} => lookup::{file}(lookup::{ty}::{}, v),",
                    camel(&e.id),
                    camel(ep)
                );
            }
        }
        s.push_str("            _ => None,\n        }\n    }\n");
    }
    s.push_str("}\n\n");
    with.push_str("        }\n    }\n}\n");
    s + &with
}
