//! A small Python pickle decoder for nuPlan's calibration columns (`camera.translation`, `rotation`,
//! `intrinsic`, `distortion`, `lidar.*`): pickled lists / tuples of numbers and pickled numpy arrays
//! (`numpy[._]core.multiarray._reconstruct` + `BUILD` with a float / int dtype and the raw bytes). Protocols 2-5;
//! only the opcodes those objects need. Anything else is an error naming the opcode and its offset.
use anyhow::{anyhow, bail, Result};

/// A decoded pickle object (only what lists and numpy arrays are made of).
#[derive(Clone, Debug, PartialEq)]
pub enum Obj {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<Obj>),
    Tuple(Vec<Obj>),
    Dict(Vec<(Obj, Obj)>),
    /// `module.name` of a GLOBAL / STACK_GLOBAL.
    Global(String),
    /// A callable applied to its arguments (REDUCE / NEWOBJ), with the state of a later BUILD.
    Call {
        func: Box<Obj>,
        args: Vec<Obj>,
        state: Option<Box<Obj>>,
    },
}

/// Longest pickle accepted (bytes): the calibration columns hold a few hundred; the bound also bounds the
/// nesting depth of what a pickle builds (one byte or more per level), so that no recursion overflows the stack.
pub const MAX_PICKLE_BYTES: usize = 4096;
/// Most objects one pickle may build, copies made by memo GETs included (GET of a list holding itself twice,
/// repeated, doubles the size each time).
pub const MAX_PICKLE_OBJECTS: usize = 1 << 20;

/// Objects in `o` (itself included; strings and byte strings count one per 64 bytes as well).
fn weight(o: &Obj) -> usize {
    match o {
        Obj::Str(t) => 1 + t.len() / 64,
        Obj::Bytes(b) => 1 + b.len() / 64,
        Obj::List(v) | Obj::Tuple(v) => 1 + v.iter().map(weight).sum::<usize>(),
        Obj::Dict(d) => 1 + d.iter().map(|(k, v)| weight(k) + weight(v)).sum::<usize>(),
        Obj::Call { func, args, state } => {
            1 + weight(func)
                + args.iter().map(weight).sum::<usize>()
                + state.as_deref().map_or(0, weight)
        }
        _ => 1,
    }
}

/// Decodes one pickle.
pub fn decode(data: &[u8]) -> Result<Obj> {
    if data.len() > MAX_PICKLE_BYTES {
        bail!(
            "pickle of {} bytes (at most {MAX_PICKLE_BYTES} are accepted)",
            data.len()
        );
    }
    // Objects built so far (each opcode builds at most one; memo GETs copy).
    let mut built = 0usize;
    let mut stack: Vec<Obj> = Vec::new();
    let mut marks: Vec<usize> = Vec::new();
    let mut memo: Vec<Option<Obj>> = Vec::new();
    let mut i = 0usize;
    fn take_from<'a>(data: &'a [u8], i: &mut usize, n: usize) -> Result<&'a [u8]> {
        let s = data
            .get(*i..i.saturating_add(n))
            .ok_or_else(|| anyhow!("pickle truncated at byte {}", *i))?;
        *i += n;
        Ok(s)
    }
    let take = |i: &mut usize, n: usize| take_from(data, i, n);
    let u32le = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    let pop = |stack: &mut Vec<Obj>, at: usize| -> Result<Obj> {
        stack
            .pop()
            .ok_or_else(|| anyhow!("pickle: stack underflow at byte {at}"))
    };
    // Memo keys are dense from 0 as Python writes them; one far past the end (LONG_BINPUT 4e9) would size the
    // memo from a 4-byte field.
    let put = |memo: &mut Vec<Option<Obj>>, k: usize, v: Obj, at: usize| -> Result<()> {
        if k > memo.len() + MAX_PICKLE_BYTES {
            bail!(
                "pickle: memo key {k} at byte {at} is far past the memo's {} entries",
                memo.len()
            );
        }
        if memo.len() <= k {
            memo.resize(k + 1, None);
        }
        memo[k] = Some(v);
        Ok(())
    };
    loop {
        let at = i;
        let op = *take(&mut i, 1)?.first().unwrap();
        built += 1;
        if built > MAX_PICKLE_OBJECTS {
            bail!("pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at}");
        }
        match op {
            0x80 => {
                let v = take(&mut i, 1)?[0];
                if !(2..=5).contains(&v) {
                    bail!("pickle protocol {v} is not supported (2 to 5 are)");
                }
            }
            0x95 => {
                take(&mut i, 8)?; // FRAME
            }
            b'.' => return pop(&mut stack, at),
            b'(' => marks.push(stack.len()),
            b']' => stack.push(Obj::List(vec![])),
            b')' => stack.push(Obj::Tuple(vec![])),
            b'}' => stack.push(Obj::Dict(vec![])),
            b'N' => stack.push(Obj::None),
            0x88 => stack.push(Obj::Bool(true)),
            0x89 => stack.push(Obj::Bool(false)),
            b'G' => {
                let b = take(&mut i, 8)?;
                stack.push(Obj::Float(f64::from_be_bytes(b.try_into().unwrap())));
            }
            b'J' => {
                let b = take(&mut i, 4)?;
                stack.push(Obj::Int(i32::from_le_bytes(b.try_into().unwrap()) as i64));
            }
            b'K' => stack.push(Obj::Int(take(&mut i, 1)?[0] as i64)),
            b'M' => {
                let b = take(&mut i, 2)?;
                stack.push(Obj::Int(u16::from_le_bytes([b[0], b[1]]) as i64));
            }
            0x8a => {
                // LONG1: little-endian two's complement of n bytes.
                let n = take(&mut i, 1)?[0] as usize;
                let b = take(&mut i, n)?;
                if n > 8 {
                    bail!("pickle: integer of {n} bytes at byte {at}");
                }
                let mut v: i64 = 0;
                for (k, &x) in b.iter().enumerate() {
                    v |= (x as i64) << (8 * k);
                }
                if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                    v -= 1i64 << (8 * n);
                }
                stack.push(Obj::Int(v));
            }
            0x8c | b'X' | 0x8d | b'U' | b'T' => {
                let n = match op {
                    0x8c | b'U' => take(&mut i, 1)?[0] as usize,
                    0x8d => u64::from_le_bytes(take(&mut i, 8)?.try_into().unwrap()) as usize,
                    _ => u32le(take(&mut i, 4)?) as usize,
                };
                let b = take(&mut i, n)?;
                let s = std::str::from_utf8(b)
                    .map_err(|_| anyhow!("pickle: string at byte {at} is not UTF-8"))?;
                stack.push(Obj::Str(s.to_string()));
            }
            b'C' | b'B' | 0x8e => {
                let n = match op {
                    b'C' => take(&mut i, 1)?[0] as usize,
                    b'B' => u32le(take(&mut i, 4)?) as usize,
                    _ => u64::from_le_bytes(take(&mut i, 8)?.try_into().unwrap()) as usize,
                };
                stack.push(Obj::Bytes(take(&mut i, n)?.to_vec()));
            }
            0x94 => {
                let top = stack
                    .last()
                    .cloned()
                    .ok_or_else(|| anyhow!("pickle: MEMOIZE on an empty stack at byte {at}"))?;
                let k = memo.len();
                built += weight(&top);
                if built > MAX_PICKLE_OBJECTS {
                    bail!("pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at} (memo copies)");
                }
                put(&mut memo, k, top, at)?;
            }
            b'q' | b'r' => {
                let k = if op == b'q' {
                    take(&mut i, 1)?[0] as usize
                } else {
                    u32le(take(&mut i, 4)?) as usize
                };
                let top = stack
                    .last()
                    .cloned()
                    .ok_or_else(|| anyhow!("pickle: PUT on an empty stack at byte {at}"))?;
                built += weight(&top);
                if built > MAX_PICKLE_OBJECTS {
                    bail!("pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at} (memo copies)");
                }
                put(&mut memo, k, top, at)?;
            }
            b'h' | b'j' => {
                let k = if op == b'h' {
                    take(&mut i, 1)?[0] as usize
                } else {
                    u32le(take(&mut i, 4)?) as usize
                };
                let v = memo
                    .get(k)
                    .cloned()
                    .flatten()
                    .ok_or_else(|| anyhow!("pickle: memo {k} unset at byte {at}"))?;
                built += weight(&v);
                if built > MAX_PICKLE_OBJECTS {
                    bail!("pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at} (memo copies)");
                }
                stack.push(v);
            }
            b'c' => {
                // GLOBAL: "module\nname\n".
                let rest = &data[i..];
                let mut lines = rest.splitn(3, |&b| b == b'\n');
                let (m, n) = (lines.next().unwrap_or(&[]), lines.next().unwrap_or(&[]));
                i += m.len() + n.len() + 2;
                if i > data.len() {
                    bail!("pickle truncated in GLOBAL at byte {at}");
                }
                stack.push(Obj::Global(format!(
                    "{}.{}",
                    String::from_utf8_lossy(m),
                    String::from_utf8_lossy(n)
                )));
            }
            0x93 => {
                let name = pop(&mut stack, at)?;
                let module = pop(&mut stack, at)?;
                match (module, name) {
                    (Obj::Str(m), Obj::Str(n)) => stack.push(Obj::Global(format!("{m}.{n}"))),
                    _ => bail!("pickle: STACK_GLOBAL needs two strings at byte {at}"),
                }
            }
            0x85..=0x87 => {
                let n = (op - 0x84) as usize;
                if stack.len() < n {
                    bail!("pickle: stack underflow at byte {at}");
                }
                let items = stack.split_off(stack.len() - n);
                stack.push(Obj::Tuple(items));
            }
            b't' | b'l' => {
                let m = marks
                    .pop()
                    .ok_or_else(|| anyhow!("pickle: no MARK at byte {at}"))?;
                let items = stack.split_off(m.min(stack.len()));
                stack.push(if op == b't' {
                    Obj::Tuple(items)
                } else {
                    Obj::List(items)
                });
            }
            b'a' => {
                let v = pop(&mut stack, at)?;
                match stack.last_mut() {
                    Some(Obj::List(l)) => l.push(v),
                    _ => bail!("pickle: APPEND to a non-list at byte {at}"),
                }
            }
            b'e' => {
                let m = marks
                    .pop()
                    .ok_or_else(|| anyhow!("pickle: no MARK at byte {at}"))?;
                let items = stack.split_off(m.min(stack.len()));
                match stack.last_mut() {
                    Some(Obj::List(l)) => l.extend(items),
                    _ => bail!("pickle: APPENDS to a non-list at byte {at}"),
                }
            }
            b's' => {
                let v = pop(&mut stack, at)?;
                let k = pop(&mut stack, at)?;
                match stack.last_mut() {
                    Some(Obj::Dict(d)) => d.push((k, v)),
                    _ => bail!("pickle: SETITEM on a non-dict at byte {at}"),
                }
            }
            b'u' => {
                let m = marks
                    .pop()
                    .ok_or_else(|| anyhow!("pickle: no MARK at byte {at}"))?;
                let items = stack.split_off(m.min(stack.len()));
                match stack.last_mut() {
                    Some(Obj::Dict(d)) => {
                        let mut it = items.into_iter();
                        while let (Some(k), Some(v)) = (it.next(), it.next()) {
                            d.push((k, v));
                        }
                    }
                    _ => bail!("pickle: SETITEMS on a non-dict at byte {at}"),
                }
            }
            b'R' | 0x81 => {
                let args = pop(&mut stack, at)?;
                let func = pop(&mut stack, at)?;
                let Obj::Tuple(args) = args else {
                    bail!("pickle: REDUCE / NEWOBJ arguments are not a tuple at byte {at}");
                };
                stack.push(Obj::Call {
                    func: Box::new(func),
                    args,
                    state: None,
                });
            }
            b'b' => {
                let st = pop(&mut stack, at)?;
                match stack.last_mut() {
                    Some(Obj::Call { state, .. }) => *state = Some(Box::new(st)),
                    _ => bail!("pickle: BUILD on a non-object at byte {at}"),
                }
            }
            other => bail!(
                "pickle: opcode 0x{other:02x} at byte {at} is not supported (lists, tuples, numbers and numpy arrays are)"
            ),
        }
    }
}

fn number(o: &Obj) -> Option<f64> {
    match o {
        Obj::Float(f) => Some(*f),
        Obj::Int(i) => Some(*i as f64),
        Obj::Bool(b) => Some(f64::from(u8::from(*b))),
        _ => None,
    }
}

/// A numeric array: (shape, values in C order).
pub fn to_array(o: &Obj) -> Result<(Vec<usize>, Vec<f64>)> {
    nested_array(o, 0)
}

/// Deepest nesting of lists accepted as an array.
const MAX_ARRAY_DEPTH: usize = 8;

fn nested_array(o: &Obj, depth: usize) -> Result<(Vec<usize>, Vec<f64>)> {
    if depth > MAX_ARRAY_DEPTH {
        bail!("lists nested deeper than {MAX_ARRAY_DEPTH} levels");
    }
    match o {
        Obj::List(v) | Obj::Tuple(v) => {
            if v.iter().all(|x| number(x).is_some()) {
                return Ok((vec![v.len()], v.iter().filter_map(number).collect()));
            }
            let mut shape: Option<Vec<usize>> = None;
            let mut out = Vec::new();
            for x in v {
                let (s, d) = nested_array(x, depth + 1)?;
                if shape.as_ref().is_some_and(|p| *p != s) {
                    bail!("ragged nested list");
                }
                shape = Some(s);
                out.extend(d);
            }
            let mut s = vec![v.len()];
            s.extend(shape.unwrap_or_default());
            Ok((s, out))
        }
        Obj::Call { func, args, state } => {
            let Obj::Global(name) = func.as_ref() else {
                bail!("not a numeric array (a call of a non-global)");
            };
            if !name.ends_with("multiarray._reconstruct") {
                bail!("not a numeric array ({name})");
            }
            let _ = args;
            let Some(Obj::Tuple(st)) = state.as_deref() else {
                bail!("numpy array without its state");
            };
            // (version, shape, dtype, is_fortran, raw bytes)
            let [_, shape, dtype, fortran, raw] = st.as_slice() else {
                bail!("numpy array state of {} items (expected 5)", st.len());
            };
            let Obj::Tuple(shape) = shape else {
                bail!("numpy array shape is not a tuple")
            };
            let shape: Vec<usize> = shape
                .iter()
                .map(|d| match d {
                    Obj::Int(n) if *n >= 0 => Ok(*n as usize),
                    _ => Err(anyhow!("numpy array shape holds {d:?}")),
                })
                .collect::<Result<_>>()?;
            if *fortran == Obj::Bool(true) && shape.len() > 1 {
                bail!("Fortran-ordered numpy arrays are not supported");
            }
            let Obj::Bytes(raw) = raw else {
                bail!("numpy array data is not bytes (object arrays are not supported)")
            };
            let (kind, big) = dtype_of(dtype)?;
            let size = dtype_size(kind);
            let n = shape
                .iter()
                .try_fold(1usize, |a, &d| a.checked_mul(d))
                .filter(|n| n.checked_mul(size).is_some())
                .ok_or_else(|| anyhow!("numpy array of shape {shape:?}: the size overflows"))?;
            if raw.len() != n * size {
                bail!(
                    "numpy array of shape {shape:?} and dtype {kind} holds {} bytes (expected {})",
                    raw.len(),
                    n * size
                );
            }
            let vals = raw
                .chunks_exact(size)
                .map(|c| {
                    let mut b = c.to_vec();
                    if big {
                        b.reverse();
                    }
                    match kind {
                        "f8" => f64::from_le_bytes(b.try_into().unwrap()),
                        "f4" => f32::from_le_bytes(b.try_into().unwrap()) as f64,
                        "i8" => i64::from_le_bytes(b.try_into().unwrap()) as f64,
                        _ => i32::from_le_bytes(b.try_into().unwrap()) as f64,
                    }
                })
                .collect();
            Ok((shape, vals))
        }
        other => bail!("not a numeric array ({})", kind_of(other)),
    }
}

/// Bytes per element of a supported dtype kind.
fn dtype_size(kind: &str) -> usize {
    if kind.ends_with('8') {
        8
    } else {
        4
    }
}

/// (kind, big-endian) of a pickled `numpy.dtype(kind, False, True)` with its BUILD state.
fn dtype_of(o: &Obj) -> Result<(&'static str, bool)> {
    let Obj::Call { func, args, state } = o else {
        bail!("numpy dtype is not an object");
    };
    if !matches!(func.as_ref(), Obj::Global(n) if n.ends_with(".dtype")) {
        bail!("numpy dtype expected, found {func:?}");
    }
    let kind = match args.first() {
        Some(Obj::Str(s)) => s.as_str(),
        _ => bail!("numpy dtype without a kind"),
    };
    let kind = match kind {
        "f8" => "f8",
        "f4" => "f4",
        "i8" => "i8",
        "i4" => "i4",
        other => bail!("numpy dtype {other:?} is not supported (f8, f4, i8, i4 are)"),
    };
    let big = match state.as_deref() {
        Some(Obj::Tuple(s)) => matches!(s.get(1), Some(Obj::Str(e)) if e == ">"),
        _ => false,
    };
    Ok((kind, big))
}

fn kind_of(o: &Obj) -> &'static str {
    match o {
        Obj::None => "None",
        Obj::Bool(_) => "a bool",
        Obj::Int(_) => "an int",
        Obj::Float(_) => "a float",
        Obj::Str(_) => "a str",
        Obj::Bytes(_) => "bytes",
        Obj::List(_) => "a list",
        Obj::Tuple(_) => "a tuple",
        Obj::Dict(_) => "a dict",
        Obj::Global(_) => "a global",
        Obj::Call { .. } => "an object",
    }
}

/// Decodes a pickled numeric array of `n` values (any shape with n elements).
pub fn floats(data: &[u8], n: usize) -> Result<Vec<f64>> {
    let (shape, v) = to_array(&decode(data)?)?;
    if v.len() != n {
        bail!("expected {n} numbers, found shape {shape:?}");
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    // pickle.dumps([1.5, 0.0, 1.8]) (protocol 4).
    const LIST: &[u8] = b"\x80\x04\x95 \x00\x00\x00\x00\x00\x00\x00]\x94(G?\xf8\x00\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G?\xfc\xcc\xcc\xcc\xcc\xcc\xcde.";

    #[test]
    fn list_of_floats() {
        assert_eq!(floats(LIST, 3).unwrap(), vec![1.5, 0.0, 1.8]);
        assert!(floats(LIST, 4).is_err());
        assert!(decode(&LIST[..20]).is_err());
    }

    #[test]
    fn protocol2_tuple_and_ints() {
        // pickle.dumps((1, -2, 300), protocol=2)
        let p = b"\x80\x02K\x01J\xfe\xff\xff\xffM,\x01\x87q\x00.";
        assert_eq!(floats(p, 3).unwrap(), vec![1.0, -2.0, 300.0]);
    }

    #[test]
    fn unsupported_opcode_is_an_error() {
        let e = decode(b"\x80\x04\xff.").unwrap_err().to_string();
        assert!(e.contains("0xff"), "{e}");
    }

    /// Hostile pickles (issue #18): a memo key from a 4-byte field, memo copies that double in size, the
    /// deepest nesting the size bound allows: errors, no huge allocation, no
    /// stack overflow.
    #[test]
    fn hostile_pickles_are_errors() {
        // LONG_BINPUT 0xffffffff
        let e = decode(b"\x80\x04]r\xff\xff\xff\xff.")
            .unwrap_err()
            .to_string();
        assert!(e.contains("memo key 4294967295"), "{e}");
        // [] memoized; then 60 times: GET 0, GET 0, TUPLE2, PUT 0 (doubles the memo's object)
        let mut p = b"\x80\x04]\x94".to_vec();
        for _ in 0..60 {
            p.extend_from_slice(b"h\x00h\x00\x86q\x00");
        }
        p.push(b'.');
        let e = decode(&p).unwrap_err().to_string();
        assert!(e.contains("objects"), "{e}");
        // the deepest nesting within MAX_PICKLE_BYTES: decoded (or refused) and dropped without overflow
        let depth = (MAX_PICKLE_BYTES - 4) / 2;
        let mut p = b"\x80\x04".to_vec();
        p.extend(std::iter::repeat_n(b']', depth));
        p.extend(std::iter::repeat_n(b'a', depth - 1));
        p.push(b'.');
        let o = decode(&p).unwrap();
        assert!(to_array(&o)
            .unwrap_err()
            .to_string()
            .contains("nested deeper"));
        drop(o);
        let mut big = p.clone();
        big.resize(MAX_PICKLE_BYTES + 1, b'.');
        assert!(decode(&big).unwrap_err().to_string().contains("at most"));
    }
}
