//! Decoded pickle objects as number arrays: what `list(pickle.loads(blob))` gives for the calibration columns
//! (module docs of [`super`]). Each form is read the way `pickle.loads` would build it; an object `list()` would
//! not turn into numbers is an error naming what was found.
use super::{kind_of, Obj, DEVKIT_LIST_CLASSES};
use anyhow::{anyhow, bail, Result};

/// Deepest nesting of lists accepted as an array.
const MAX_ARRAY_DEPTH: usize = 8;

/// A numeric array: (shape, values in C order).
pub fn to_array(o: &Obj) -> Result<(Vec<usize>, Vec<f64>)> {
    nested_array(o, 0)
}

fn number(o: &Obj) -> Option<f64> {
    match o {
        Obj::Float(f) => Some(*f),
        Obj::Int(i) => Some(*i as f64),
        Obj::Bool(b) => Some(f64::from(u8::from(*b))),
        _ => None,
    }
}

/// The global's dotted name when `o` is one.
fn global(o: &Obj) -> Option<&str> {
    match o {
        Obj::Global(g) => Some(g),
        _ => None,
    }
}

/// `list` itself (Python 3 and the protocol-2 name) or one of [`DEVKIT_LIST_CLASSES`].
fn is_list_class(o: &Obj) -> bool {
    global(o).is_some_and(|n| {
        matches!(n, "builtins.list" | "__builtin__.list") || DEVKIT_LIST_CLASSES.contains(&n)
    })
}

/// numpy's module of `name` (`numpy.core.multiarray.<name>` before numpy 2, `numpy._core.multiarray.<name>`
/// after).
fn is_numpy(o: &Obj, name: &str) -> bool {
    global(o).is_some_and(|g| {
        g.strip_suffix(name)
            .is_some_and(|m| matches!(m, "numpy.core.multiarray." | "numpy._core.multiarray."))
    })
}

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
        Obj::Call { func, .. } if is_numpy(func, "_reconstruct") => numpy_array(o),
        Obj::Call { func, args, .. } if is_numpy(func, "scalar") => {
            let [dtype, raw] = args.as_slice() else {
                bail!("numpy scalar of {} arguments (expected 2)", args.len());
            };
            let (_, v) = values(dtype, &bytes_of(raw)?, 1)?;
            Ok((vec![], v))
        }
        Obj::Call { .. } => {
            let items = list_items(o)?;
            nested_array(&Obj::List(items), depth + 1)
        }
        other => bail!("not a numeric array (found {})", kind_of(other)),
    }
}

/// The elements of a list (sub)class instance as `pickle.loads` builds it: the constructor's elements, then
/// APPEND(S), then SETITEM(S) (`obj[i] = v`, i an index within the list). Forms:
/// - `NEWOBJ(cls, args)`: `cls.__new__(cls, *args)`, empty (list's `__new__` ignores its arguments; this is
///   what protocols 2-5 write for a list subclass, with `args = ()`);
/// - `REDUCE(cls, (iterable,))` / `REDUCE(cls, ())`: `cls(iterable)`, its elements;
/// - `REDUCE(copyreg._reconstructor, (cls, list, state))`: protocols 0-1 of a list subclass, `state`'s elements;
/// - `REDUCE(copyreg.__newobj__, (cls, *args))`: as NEWOBJ.
fn list_items(o: &Obj) -> Result<Vec<Obj>> {
    let Obj::Call {
        func,
        newobj,
        args,
        items,
        set_items,
        ..
    } = o
    else {
        bail!("not a numeric array (found {})", kind_of(o));
    };
    let name = global(func).unwrap_or("");
    let mut out: Vec<Obj> = if *newobj && is_list_class(func) {
        vec![]
    } else if is_list_class(func) {
        match args.as_slice() {
            [] => vec![],
            [it] => elements(it)?,
            _ => bail!("{name} called with {} arguments", args.len()),
        }
    } else if matches!(name, "copyreg._reconstructor" | "copy_reg._reconstructor") {
        match args.as_slice() {
            [cls, base, state] if is_list_class(cls) && is_list_class(base) => elements(state)?,
            [cls, base, _] if is_list_class(cls) => bail!(
                "{} rebuilt on {} (only list subclasses are number arrays)",
                global(cls).unwrap_or("?"),
                kind_of(base)
            ),
            [cls, ..] => bail!(
                "not a numeric array (found {} rebuilt by {name}; list and the list subclasses of \
                 nuplan.database.common.data_types are read)",
                kind_of(cls)
            ),
            _ => bail!("{name} called with {} arguments (expected 3)", args.len()),
        }
    } else if matches!(name, "copyreg.__newobj__" | "copy_reg.__newobj__")
        && args.first().is_some_and(is_list_class)
    {
        vec![]
    } else {
        bail!(
            "not a numeric array (found {}; lists, numpy arrays and the list subclasses of \
             nuplan.database.common.data_types are read)",
            kind_of(o)
        );
    };
    out.extend(items.iter().cloned());
    for (k, v) in set_items {
        let n = out.len() as i64;
        let i = match k {
            Obj::Int(i) if (-n..n).contains(i) => i.rem_euclid(n.max(1)) as usize,
            _ => bail!(
                "{name}: item assignment at {} of a list of {n} elements",
                kind_of(k)
            ),
        };
        out[i] = v.clone();
    }
    Ok(out)
}

/// What `list(o)` iterates over, for the argument of a list constructor: a list or tuple's elements, a list
/// subclass's, a numpy array's rows (1-d: its numbers).
fn elements(o: &Obj) -> Result<Vec<Obj>> {
    match o {
        Obj::List(v) | Obj::Tuple(v) => Ok(v.clone()),
        Obj::Call { func, .. } if is_numpy(func, "_reconstruct") => {
            let (shape, v) = numpy_array(o)?;
            match shape.as_slice() {
                [_] => Ok(v.into_iter().map(Obj::Float).collect()),
                [rows, ..] => {
                    let w = v.len() / (*rows).max(1);
                    Ok(v.chunks(w.max(1))
                        .map(|r| Obj::List(r.iter().map(|x| Obj::Float(*x)).collect()))
                        .collect())
                }
                [] => bail!("iteration over a 0-d numpy array"),
            }
        }
        Obj::Call { .. } => list_items(o),
        other => bail!(
            "a list built from {} (an iterable expected)",
            kind_of(other)
        ),
    }
}

/// The raw bytes of a pickled `bytes`: the object itself (protocol 3+), or protocol 2's
/// `_codecs.encode(str, "latin1")` / `bytes()`.
fn bytes_of(o: &Obj) -> Result<Vec<u8>> {
    match o {
        Obj::Bytes(b) => Ok(b.clone()),
        Obj::Call { func, args, .. } => match (global(func).unwrap_or(""), args.as_slice()) {
            ("_codecs.encode", [Obj::Str(s), Obj::Str(enc)])
                if matches!(enc.as_str(), "latin1" | "latin-1") =>
            {
                s.chars()
                    .map(|c| {
                        u8::try_from(u32::from(c)).map_err(|_| anyhow!("{c:?} is not latin-1"))
                    })
                    .collect()
            }
            ("builtins.bytes" | "__builtin__.bytes", []) => Ok(vec![]),
            _ => bail!("bytes expected, found {}", kind_of(o)),
        },
        other => bail!(
            "numpy data is not bytes (found {}; object arrays are not supported)",
            kind_of(other)
        ),
    }
}

/// A pickled numpy array: `_reconstruct(ndarray, (0,), b"b")` + `BUILD((version, shape, dtype, is_fortran,
/// raw bytes))`.
fn numpy_array(o: &Obj) -> Result<(Vec<usize>, Vec<f64>)> {
    let Obj::Call { state, items, .. } = o else {
        bail!("not a numpy array");
    };
    if !items.is_empty() {
        bail!("APPEND to a numpy array (ndarray has no append)");
    }
    let Some(Obj::Tuple(st)) = state.as_deref() else {
        bail!("numpy array without its state");
    };
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
            _ => Err(anyhow!("numpy array shape holds {}", kind_of(d))),
        })
        .collect::<Result<_>>()?;
    if *fortran == Obj::Bool(true) && shape.len() > 1 {
        bail!("Fortran-ordered numpy arrays are not supported");
    }
    let n = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .filter(|n| n.checked_mul(8).is_some())
        .ok_or_else(|| anyhow!("numpy array of shape {shape:?}: the size overflows"))?;
    let (kind, v) = values(dtype, &bytes_of(raw)?, n)?;
    if v.len() != n {
        bail!(
            "numpy array of shape {shape:?} and dtype {kind} holds {} values",
            v.len()
        );
    }
    Ok((shape, v))
}

/// `n` values of the pickled `dtype` from `raw` (exactly `n` elements' bytes).
fn values(dtype: &Obj, raw: &[u8], n: usize) -> Result<(&'static str, Vec<f64>)> {
    let (kind, big) = dtype_of(dtype)?;
    let size = dtype_size(kind);
    if raw.len() != n * size {
        bail!(
            "numpy data of {} bytes for {n} values of dtype {kind} (expected {})",
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
    Ok((kind, vals))
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
    let Obj::Call {
        func, args, state, ..
    } = o
    else {
        bail!("numpy dtype expected, found {}", kind_of(o));
    };
    if !matches!(func.as_ref(), Obj::Global(n) if n.ends_with(".dtype")) {
        bail!("numpy dtype expected, found {}", kind_of(o));
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
