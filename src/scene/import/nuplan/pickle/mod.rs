//! A small Python pickle decoder for nuPlan's calibration columns (`camera.translation`, `rotation`,
//! `intrinsic`, `distortion`, `lidar.*`). The devkit stores them through `SimplePickleType`
//! (nuplan/database/common/sql_types.py): `pickle.dumps(value)` of whatever it was given, read back as
//! `class_type(pickle.loads(blob))`. So every object that `list()` turns into numbers is a valid value, and
//! [`to_array`] reads each of these forms:
//! - lists / tuples of numbers (nested for the 3x3 intrinsic);
//! - numpy arrays (`numpy[._]core.multiarray._reconstruct` + `BUILD` with a float / int dtype and the raw bytes)
//!   and numpy scalars (`numpy[._]core.multiarray.scalar`), also inside lists;
//! - the devkit's list subclasses of `nuplan.database.common.data_types` (Translation, Rotation, CameraIntrinsic,
//!   Size, Bbox): `cls` + `NEWOBJ` + `APPENDS` (protocol 2+, what `pickle.dumps(Translation([...]))` writes), or
//!   `copyreg._reconstructor(cls, list, [...])` / `cls([...])` by `REDUCE`, each optionally followed by
//!   `APPEND(S)` / `SETITEM(S)` and a `BUILD` of the instance dict (ignored: `list()` does not read it).
//!
//! Protocols 0-5 (protocol 0's text opcodes for numbers, strings and the memo; protocols 0-2's bytes as
//! `_codecs.encode(str, "latin1")`); only the opcodes those objects need. Anything else is an error naming the
//! opcode and its offset, or the object found.
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
    /// A callable applied to its arguments (REDUCE), or a class's `__new__` (NEWOBJ: `newobj`), with the state
    /// of a later BUILD and what later APPEND(S) / SETITEM(S) added to the object it built (a list or dict
    /// subclass).
    Call {
        func: Box<Obj>,
        newobj: bool,
        args: Vec<Obj>,
        state: Option<Box<Obj>>,
        items: Vec<Obj>,
        set_items: Vec<(Obj, Obj)>,
    },
}

/// The list subclasses of nuplan-devkit's `nuplan.database.common.data_types` (`class X(List[float])` /
/// `List[int]` / `List[List[float]]`); `RLE` (a dict) and `Visibility` (an enum) are not number arrays.
pub const DEVKIT_LIST_CLASSES: [&str; 5] = [
    "nuplan.database.common.data_types.Translation",
    "nuplan.database.common.data_types.Rotation",
    "nuplan.database.common.data_types.CameraIntrinsic",
    "nuplan.database.common.data_types.Size",
    "nuplan.database.common.data_types.Bbox",
];

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
        Obj::Call {
            func,
            args,
            state,
            items,
            set_items,
            ..
        } => {
            1 + weight(func)
                + args.iter().map(weight).sum::<usize>()
                + state.as_deref().map_or(0, weight)
                + items.iter().map(weight).sum::<usize>()
                + set_items
                    .iter()
                    .map(|(k, v)| weight(k) + weight(v))
                    .sum::<usize>()
        }
        _ => 1,
    }
}

/// The unpickler's stack. Python's memo holds references, so an object mutated after it was memoized
/// (APPEND(S), SETITEM(S) and BUILD follow the MEMOIZE / PUT of what they fill) is seen complete by a later GET:
/// each entry carries an identity, GET pushes the memo's identity again, and a mutation of the top entry updates
/// the memo entries of that identity ([`Stack::sync_memo`]). Copies already placed inside other objects are
/// not updated; the pickler only refers to an object again after writing it whole, except for cycles.
struct Stack {
    v: Vec<(Obj, u64)>,
    next_id: u64,
}

/// Memo entries: the object and the identity of the stack entry it was stored from.
type Memo = Vec<Option<(Obj, u64)>>;

impl Stack {
    fn push(&mut self, o: Obj) {
        self.next_id += 1;
        self.v.push((o, self.next_id));
    }
    fn pop(&mut self, at: usize) -> Result<Obj> {
        self.v
            .pop()
            .map(|x| x.0)
            .ok_or_else(|| anyhow!("pickle: stack underflow at byte {at}"))
    }
    fn len(&self) -> usize {
        self.v.len()
    }
    fn split_off(&mut self, m: usize) -> Vec<Obj> {
        self.v
            .split_off(m.min(self.v.len()))
            .into_iter()
            .map(|x| x.0)
            .collect()
    }
    fn last(&self) -> Option<&(Obj, u64)> {
        self.v.last()
    }
    fn last_mut(&mut self) -> Option<&mut Obj> {
        self.v.last_mut().map(|x| &mut x.0)
    }
    /// After the top entry was mutated: the memo entries of its identity take its new value (each copy counts
    /// against `built`).
    fn sync_memo(&self, memo: &mut Memo, built: &mut usize, at: usize) -> Result<()> {
        let Some((top, id)) = self.v.last() else {
            return Ok(());
        };
        for e in memo.iter_mut().flatten() {
            if e.1 == *id {
                *built += weight(top);
                if *built > MAX_PICKLE_OBJECTS {
                    bail!(
                        "pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at} (memo copies)"
                    );
                }
                e.0 = top.clone();
            }
        }
        Ok(())
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
    let mut stack = Stack {
        v: Vec::new(),
        next_id: 0,
    };
    let mut marks: Vec<usize> = Vec::new();
    let mut memo: Memo = Vec::new();
    let mut i = 0usize;
    fn take_from<'a>(data: &'a [u8], i: &mut usize, n: usize) -> Result<&'a [u8]> {
        let s = data
            .get(*i..i.saturating_add(n))
            .ok_or_else(|| anyhow!("pickle truncated at byte {}", *i))?;
        *i += n;
        Ok(s)
    }
    let take = |i: &mut usize, n: usize| take_from(data, i, n);
    // The bytes up to the next newline (protocol 0's text arguments), the newline skipped.
    let line = |i: &mut usize| -> Result<&[u8]> {
        let rest = &data[*i..];
        let n = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| anyhow!("pickle truncated in a text argument at byte {}", *i))?;
        *i += n + 1;
        Ok(&rest[..n])
    };
    let u32le = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    // Memo keys are dense from 0 as Python writes them; one far past the end (LONG_BINPUT 4e9) would size the
    // memo from a 4-byte field.
    let put = |memo: &mut Memo, k: usize, v: (Obj, u64), at: usize| -> Result<()> {
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
                    bail!("pickle protocol {v} is not supported (0 to 5 are; 0 and 1 have no PROTO opcode)");
                }
            }
            0x95 => {
                take(&mut i, 8)?; // FRAME
            }
            b'.' => return stack.pop(at),
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
                built += weight(&top.0);
                if built > MAX_PICKLE_OBJECTS {
                    bail!("pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at} (memo copies)");
                }
                put(&mut memo, k, top, at)?;
            }
            b'q' | b'r' | b'p' => {
                let k = match op {
                    b'q' => take(&mut i, 1)?[0] as usize,
                    b'r' => u32le(take(&mut i, 4)?) as usize,
                    _ => parse_line::<usize>(line(&mut i)?, "PUT", at)?,
                };
                let top = stack
                    .last()
                    .cloned()
                    .ok_or_else(|| anyhow!("pickle: PUT on an empty stack at byte {at}"))?;
                built += weight(&top.0);
                if built > MAX_PICKLE_OBJECTS {
                    bail!("pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at} (memo copies)");
                }
                put(&mut memo, k, top, at)?;
            }
            b'h' | b'j' | b'g' => {
                let k = match op {
                    b'h' => take(&mut i, 1)?[0] as usize,
                    b'j' => u32le(take(&mut i, 4)?) as usize,
                    _ => parse_line::<usize>(line(&mut i)?, "GET", at)?,
                };
                let (v, id) = memo
                    .get(k)
                    .cloned()
                    .flatten()
                    .ok_or_else(|| anyhow!("pickle: memo {k} unset at byte {at}"))?;
                built += weight(&v);
                if built > MAX_PICKLE_OBJECTS {
                    bail!("pickle: more than {MAX_PICKLE_OBJECTS} objects at byte {at} (memo copies)");
                }
                stack.v.push((v, id));
            }
            // Protocol 0's text opcodes (what `pickle.dumps(x, protocol=0)` writes for numbers, strings and
            // the memo): FLOAT, INT (01 / 00: True / False), LONG (a trailing L allowed), UNICODE
            // (raw-unicode-escape).
            b'F' => {
                let v = parse_line::<f64>(line(&mut i)?, "FLOAT", at)?;
                stack.push(Obj::Float(v));
            }
            b'I' => {
                let l = line(&mut i)?;
                stack.push(match l {
                    b"01" => Obj::Bool(true),
                    b"00" => Obj::Bool(false),
                    _ => Obj::Int(parse_line::<i64>(l, "INT", at)?),
                });
            }
            b'L' => {
                let l = line(&mut i)?;
                let l = l.strip_suffix(b"L").unwrap_or(l);
                stack.push(Obj::Int(parse_line::<i64>(l, "LONG", at)?));
            }
            b'V' => {
                let l = line(&mut i)?;
                stack.push(Obj::Str(raw_unicode_escape(l).ok_or_else(|| {
                    anyhow!("pickle: UNICODE at byte {at} is not raw-unicode-escape text")
                })?));
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
                let name = stack.pop(at)?;
                let module = stack.pop(at)?;
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
            b'd' => {
                let m = marks
                    .pop()
                    .ok_or_else(|| anyhow!("pickle: no MARK at byte {at}"))?;
                let kv = stack.split_off(m);
                let mut d = Vec::with_capacity(kv.len() / 2);
                let mut it = kv.into_iter();
                while let (Some(k), Some(v)) = (it.next(), it.next()) {
                    d.push((k, v));
                }
                stack.push(Obj::Dict(d));
            }
            b't' | b'l' => {
                let m = marks
                    .pop()
                    .ok_or_else(|| anyhow!("pickle: no MARK at byte {at}"))?;
                let items = stack.split_off(m);
                stack.push(if op == b't' {
                    Obj::Tuple(items)
                } else {
                    Obj::List(items)
                });
            }
            // APPEND(S) to a list, or to an object built by REDUCE / NEWOBJ (a list subclass: pickle.loads calls
            // its `extend` / `append`).
            b'a' | b'e' => {
                let new = if op == b'a' {
                    vec![stack.pop(at)?]
                } else {
                    let m = marks
                        .pop()
                        .ok_or_else(|| anyhow!("pickle: no MARK at byte {at}"))?;
                    stack.split_off(m)
                };
                match stack.last_mut() {
                    Some(Obj::List(l)) => l.extend(new),
                    Some(Obj::Call { items, .. }) => items.extend(new),
                    Some(o) => bail!(
                        "pickle: APPEND(S) to {} at byte {at} (a list or an object built by REDUCE / NEWOBJ expected)",
                        kind_of(o)
                    ),
                    None => bail!("pickle: APPEND(S) on an empty stack at byte {at}"),
                }
                stack.sync_memo(&mut memo, &mut built, at)?;
            }
            // SETITEM(S) on a dict, or on an object built by REDUCE / NEWOBJ (its `__setitem__`).
            b's' | b'u' => {
                let kv = if op == b's' {
                    let v = stack.pop(at)?;
                    let k = stack.pop(at)?;
                    vec![k, v]
                } else {
                    let m = marks
                        .pop()
                        .ok_or_else(|| anyhow!("pickle: no MARK at byte {at}"))?;
                    stack.split_off(m)
                };
                let mut pairs = Vec::with_capacity(kv.len() / 2);
                let mut it = kv.into_iter();
                while let (Some(k), Some(v)) = (it.next(), it.next()) {
                    pairs.push((k, v));
                }
                match stack.last_mut() {
                    Some(Obj::Dict(d)) => d.extend(pairs),
                    Some(Obj::Call { set_items, .. }) => set_items.extend(pairs),
                    Some(o) => bail!(
                        "pickle: SETITEM(S) on {} at byte {at} (a dict or an object built by REDUCE / NEWOBJ expected)",
                        kind_of(o)
                    ),
                    None => bail!("pickle: SETITEM(S) on an empty stack at byte {at}"),
                }
                stack.sync_memo(&mut memo, &mut built, at)?;
            }
            b'R' | 0x81 => {
                let args = stack.pop(at)?;
                let func = stack.pop(at)?;
                let Obj::Tuple(args) = args else {
                    bail!(
                        "pickle: REDUCE / NEWOBJ arguments are {} at byte {at} (a tuple expected)",
                        kind_of(&args)
                    );
                };
                stack.push(Obj::Call {
                    func: Box::new(func),
                    newobj: op == 0x81,
                    args,
                    state: None,
                    items: vec![],
                    set_items: vec![],
                });
            }
            b'b' => {
                let st = stack.pop(at)?;
                match stack.last_mut() {
                    Some(Obj::Call { state, .. }) => *state = Some(Box::new(st)),
                    _ => bail!("pickle: BUILD on a non-object at byte {at}"),
                }
                stack.sync_memo(&mut memo, &mut built, at)?;
            }
            other => bail!(
                "pickle: opcode 0x{other:02x} at byte {at} is not supported (lists, tuples, numbers and numpy arrays are)"
            ),
        }
    }
}

mod array;
pub use array::to_array;

/// A protocol-0 text argument as a `T` (`what`: the opcode, for the error).
fn parse_line<T: std::str::FromStr>(l: &[u8], what: &str, at: usize) -> Result<T> {
    std::str::from_utf8(l)
        .ok()
        .and_then(|t| t.trim().parse::<T>().ok())
        .ok_or_else(|| {
            anyhow!(
                "pickle: {what} at byte {at}: {:?} is not a number",
                String::from_utf8_lossy(l)
            )
        })
}

/// Python's raw-unicode-escape decoding: Latin-1 bytes, `\uXXXX` and `\UXXXXXXXX` escapes.
fn raw_unicode_escape(l: &[u8]) -> Option<String> {
    let mut out = String::new();
    let mut k = 0;
    while k < l.len() {
        let n = match (l[k], l.get(k + 1)) {
            (b'\\', Some(b'u')) => 4,
            (b'\\', Some(b'U')) => 8,
            (b, _) => {
                out.push(char::from(b));
                k += 1;
                continue;
            }
        };
        let hex = std::str::from_utf8(l.get(k + 2..k + 2 + n)?).ok()?;
        out.push(char::from_u32(u32::from_str_radix(hex, 16).ok()?)?);
        k += 2 + n;
    }
    Some(out)
}

/// What `o` is, for error messages: its kind, or the callable that built it.
fn kind_of(o: &Obj) -> String {
    match o {
        Obj::None => "None".into(),
        Obj::Bool(_) => "a bool".into(),
        Obj::Int(_) => "an int".into(),
        Obj::Float(_) => "a float".into(),
        Obj::Str(_) => "a str".into(),
        Obj::Bytes(_) => "bytes".into(),
        Obj::List(_) => "a list".into(),
        Obj::Tuple(_) => "a tuple".into(),
        Obj::Dict(_) => "a dict".into(),
        Obj::Global(g) => format!("the global {g}"),
        Obj::Call { func, .. } => match func.as_ref() {
            Obj::Global(g) => format!("an object built by {g}"),
            f => format!("an object built by {}", kind_of(f)),
        },
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

    // pickle.dumps(Translation([1.5, 0.0, 1.8]), protocol=P) with nuplan-devkit's data_types classes
    // (python/tests/fixtures/nuplan_devkit), Python 3.11: protocols 0 and 1 rebuild the subclass with
    // copy_reg._reconstructor, 2+ write the class, NEWOBJ and APPENDS.
    const TRANSLATION: [&[u8]; 4] = [
        b"ccopy_reg\x0a_reconstructor\x0ap0\x0a(cnuplan.database.common.data_types\x0aTranslation\x0ap1\x0ac__builtin__\x0alist\x0ap2\x0a(lp3\x0aF1.5\x0aaF0.0\x0aaF1.8\x0aatp4\x0aRp5\x0a.",
        b"ccopy_reg\x0a_reconstructor\x0aq\x00(cnuplan.database.common.data_types\x0aTranslation\x0aq\x01c__builtin__\x0alist\x0aq\x02]q\x03(G?\xf8\x00\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G?\xfc\xcc\xcc\xcc\xcc\xcc\xcdetq\x04Rq\x05.",
        b"\x80\x02cnuplan.database.common.data_types\x0aTranslation\x0aq\x00)\x81q\x01(G?\xf8\x00\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G?\xfc\xcc\xcc\xcc\xcc\xcc\xcde.",
        b"\x80\x04\x95U\x00\x00\x00\x00\x00\x00\x00\x8c!nuplan.database.common.data_types\x94\x8c\x0bTranslation\x94\x93\x94)\x81\x94(G?\xf8\x00\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G?\xfc\xcc\xcc\xcc\xcc\xcc\xcde.",
    ];

    #[test]
    fn devkit_list_subclasses() {
        for (p, b) in TRANSLATION.iter().enumerate() {
            assert_eq!(floats(b, 3).unwrap(), vec![1.5, 0.0, 1.8], "protocol {p}");
        }
        // CameraIntrinsic([[1000, 0, 960], [0, 1000, 540], [0, 0, 1]]) (protocol 4)
        let k = b"\x80\x04\x95\x9b\x00\x00\x00\x00\x00\x00\x00\x8c!nuplan.database.common.data_types\x94\x8c\x0fCameraIntrinsic\x94\x93\x94)\x81\x94(]\x94(G@\x8f@\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G@\x8e\x00\x00\x00\x00\x00\x00e]\x94(G\x00\x00\x00\x00\x00\x00\x00\x00G@\x8f@\x00\x00\x00\x00\x00G@\x80\xe0\x00\x00\x00\x00\x00e]\x94(G\x00\x00\x00\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G?\xf0\x00\x00\x00\x00\x00\x00ee.";
        let (shape, v) = to_array(&decode(k).unwrap()).unwrap();
        assert_eq!(shape, vec![3, 3]);
        assert_eq!(
            v,
            vec![1000.0, 0.0, 960.0, 0.0, 1000.0, 540.0, 0.0, 0.0, 1.0]
        );
        // r = [0, 0, 1]; CameraIntrinsic([[2, 0, 1], r, r]): the third row is a memo GET of the second, which
        // was memoized empty and filled by APPENDS afterwards (Python's memo holds references).
        let shared = b"\x80\x04\x95~\x00\x00\x00\x00\x00\x00\x00\x8c!nuplan.database.common.data_types\x94\x8c\x0fCameraIntrinsic\x94\x93\x94)\x81\x94(]\x94(G@\x00\x00\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G?\xf0\x00\x00\x00\x00\x00\x00e]\x94(G\x00\x00\x00\x00\x00\x00\x00\x00G\x00\x00\x00\x00\x00\x00\x00\x00G?\xf0\x00\x00\x00\x00\x00\x00eh\x05e.";
        assert_eq!(
            floats(shared, 9).unwrap(),
            vec![2.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]
        );
        // Rotation([1, 0, 0, 0]), protocol 0
        let r = b"ccopy_reg\x0a_reconstructor\x0ap0\x0a(cnuplan.database.common.data_types\x0aRotation\x0ap1\x0ac__builtin__\x0alist\x0ap2\x0a(lp3\x0aF1.0\x0aaF0.0\x0aaF0.0\x0aaF0.0\x0aatp4\x0aRp5\x0a.";
        assert_eq!(floats(r, 4).unwrap(), vec![1.0, 0.0, 0.0, 0.0]);
    }

    /// Objects `list()` does not turn into numbers are errors that say what was found.
    #[test]
    fn other_objects_are_named() {
        // RLE({"size": [1, 2]}): a dict subclass of data_types (NEWOBJ + SETITEM)
        let rle = b"\x80\x04\x95@\x00\x00\x00\x00\x00\x00\x00\x8c!nuplan.database.common.data_types\x94\x8c\x03RLE\x94\x93\x94)\x81\x94\x8c\x04size\x94]\x94(K\x01K\x02es.";
        let e = to_array(&decode(rle).unwrap()).unwrap_err().to_string();
        assert!(
            e.contains("an object built by nuplan.database.common.data_types.RLE"),
            "{e}"
        );
        // Translation's pickle with the class renamed (same length): not a known list subclass
        let mut other = TRANSLATION[3].to_vec();
        let at = other.windows(11).position(|w| w == b"Translation").unwrap();
        other[at..at + 11].copy_from_slice(b"Translatiom");
        let e = floats(&other, 3).unwrap_err().to_string();
        assert!(e.contains("data_types.Translatiom"), "{e}");
        // a dict
        let e = floats(b"\x80\x04}\x94.", 3).unwrap_err().to_string();
        assert!(e.contains("found a dict"), "{e}");
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
