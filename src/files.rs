//! Reading files that arrive from outside (issue #36, item 3): a path that must name a regular file is checked
//! before it is opened, so a FIFO, a device or a socket is refused at once instead of blocking a read forever or
//! streaming without end; reads are bounded by the size the caller expects (a header's announcement, a table's
//! image size) or by a stated ceiling, never by what the other end keeps sending.
//!
//! A leaf module: it imports nothing of b2dr, so every layer may use it.
use std::fs::File;
use std::io::Read;
use std::path::Path;

use anyhow::{bail, Context, Result};

/// What a path names, in words, when it is not a regular file (`None` for a regular file).
fn not_regular(meta: &std::fs::Metadata) -> Option<&'static str> {
    let t = meta.file_type();
    if t.is_file() {
        return None;
    }
    if t.is_dir() {
        return Some("a directory");
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return Some("a FIFO (named pipe)");
        }
        if t.is_socket() {
            return Some("a socket");
        }
        if t.is_char_device() {
            return Some("a character device");
        }
        if t.is_block_device() {
            return Some("a block device");
        }
    }
    Some("not a regular file")
}

/// Checks that `path` names a regular file (symbolic links followed); returns its size in bytes. `what` says
/// what the file is for, in errors.
pub fn regular_file(path: &Path, what: &str) -> Result<u64> {
    let meta = std::fs::metadata(path)
        .with_context(|| format!("{what} {}: cannot stat", path.display()))?;
    if let Some(kind) = not_regular(&meta) {
        bail!(
            "{what} {} is {kind}, not a regular file: refused (b2dr reads only regular files)",
            path.display()
        );
    }
    Ok(meta.len())
}

/// Opens a regular file; the type is checked on the opened handle too (the path may have been swapped between
/// the check and the open). Returns the handle and its size.
pub fn open_regular(path: &Path, what: &str) -> Result<(File, u64)> {
    regular_file(path, what)?;
    // O_NONBLOCK would be needed to open a FIFO without blocking; the check above refuses one before the open,
    // and the handle's own type is checked again here
    let f = File::open(path).with_context(|| format!("{what} {}: cannot open", path.display()))?;
    let meta = f
        .metadata()
        .with_context(|| format!("{what} {}: cannot stat", path.display()))?;
    if let Some(kind) = not_regular(&meta) {
        bail!(
            "{what} {} is {kind}, not a regular file: refused",
            path.display()
        );
    }
    Ok((f, meta.len()))
}

/// Reads a whole regular file of at most `limit` bytes (a file larger than that is refused, naming both sizes).
pub fn read_regular(path: &Path, what: &str, limit: u64) -> Result<Vec<u8>> {
    let (f, len) = open_regular(path, what)?;
    if len > limit {
        bail!(
            "{what} {} is {len} bytes, more than the {limit} bytes b2dr reads for it",
            path.display()
        );
    }
    let mut out = Vec::with_capacity(len as usize);
    // the file may grow after the stat: read at most one byte more than it announced, and refuse a change
    f.take(len + 1)
        .read_to_end(&mut out)
        .with_context(|| format!("reading {what} {}", path.display()))?;
    if out.len() as u64 != len {
        bail!(
            "{what} {} changed size while it was read ({len} bytes announced, {} read)",
            path.display(),
            out.len()
        );
    }
    Ok(out)
}

/// Reads a whole regular file as UTF-8 text of at most `limit` bytes.
pub fn read_regular_string(path: &Path, what: &str, limit: u64) -> Result<String> {
    let bytes = read_regular(path, what, limit)?;
    String::from_utf8(bytes).with_context(|| format!("{what} {} is not UTF-8 text", path.display()))
}

/// The ceiling for a JSON document b2dr reads whole (scenarios, tables, maps, configurations): 4 GiB.
pub const JSON_LIMIT: u64 = 4 << 30;
/// The ceiling for a model package's text context (context.safetensors: a few (77, D) embeddings, ~1 MB for
/// SD1.5's six cameras): 256 MiB.
pub const CONTEXT_LIMIT: u64 = 256 << 20;
/// The ceiling for one recorded image file: 256 MiB (a 16384 x 16384 RGBA PNG stored is 1 GiB raw, but no camera
/// image b2dr reads approaches this compressed).
pub const IMAGE_LIMIT: u64 = 256 << 20;
