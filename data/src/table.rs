//! Parquet columns as plain Rust values: per-frame vectors (list, large list and fixed-size list
//! columns, as pyarrow and Hugging Face `datasets` write them, or scalar columns as 1-wide rows),
//! scalar numbers and string lists. A missing column is an `UnknownColumn` defect.

use std::fs::File;
use std::ops::Range;
use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use arrow_array::cast::AsArray;
use arrow_array::types::{
    Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type, UInt16Type, UInt32Type, UInt64Type, UInt8Type,
};
use arrow_array::{Array, ArrayRef, RecordBatch};
use arrow_schema::DataType;
use parquet::arrow::arrow_reader::{ParquetRecordBatchReaderBuilder, RowSelection, RowSelector};
use parquet::arrow::ProjectionMask;

use crate::defect::{defect, DefectKind};

/// Rows of a parquet file according to its footer (no data read).
pub fn num_rows(path: &Path) -> Result<usize> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let builder = ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("{}: not a readable parquet file", path.display()))?;
    usize::try_from(builder.metadata().file_metadata().num_rows()).with_context(|| format!("{}: negative row count", path.display()))
}

/// Reads `columns` of the rows in `rows` (all rows when None).
pub fn read_columns(path: &Path, columns: &[&str], rows: Option<Range<usize>>) -> Result<Vec<RecordBatch>> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let builder = ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("{}: not a readable parquet file", path.display()))?;
    let schema = builder.schema().clone();
    let mut roots = Vec::with_capacity(columns.len());
    for &name in columns {
        let Some((i, _)) = schema.column_with_name(name) else {
            let names: Vec<_> = schema.fields().iter().map(|f| f.name().as_str()).collect();
            return defect(DefectKind::UnknownColumn, format!("{}: no column '{name}' (columns: {})", path.display(), names.join(", ")));
        };
        roots.push(i);
    }
    let mask = ProjectionMask::roots(builder.parquet_schema(), roots);
    let mut builder = builder.with_projection(mask);
    if let Some(rows) = rows {
        let total = usize::try_from(builder.metadata().file_metadata().num_rows()).unwrap_or(0);
        if rows.end > total || rows.start > rows.end {
            return defect(
                DefectKind::CountMismatch,
                format!("{}: rows {}..{} requested but the file has {total}", path.display(), rows.start, rows.end),
            );
        }
        builder = builder.with_row_selection(RowSelection::from(vec![RowSelector::skip(rows.start), RowSelector::select(rows.len())]));
    }
    let reader = builder.build().with_context(|| format!("reading {}", path.display()))?;
    reader.map(|b| b.with_context(|| format!("reading {}", path.display()))).collect()
}

fn column<'a>(batch: &'a RecordBatch, name: &str, path: &Path) -> Result<&'a ArrayRef> {
    batch.column_by_name(name).with_context(|| format!("{}: column '{name}' missing from a record batch", path.display()))
}

/// One f32 vector per row of a list-of-numbers column, or a 1-wide vector per row of a scalar
/// numeric column. Nulls are `NonFinite` defects.
pub fn vectors(batches: &[RecordBatch], name: &str, path: &Path) -> Result<Vec<Vec<f32>>> {
    let mut rows = Vec::new();
    for batch in batches {
        let col = column(batch, name, path)?;
        if col.null_count() > 0 {
            let i = (0..col.len()).find(|&i| col.is_null(i)).unwrap_or(0);
            return defect(DefectKind::NonFinite, format!("{}: column '{name}' is null in row {}", path.display(), rows.len() + i));
        }
        let per_row = |values: &ArrayRef, offsets: &mut dyn Iterator<Item = (usize, usize)>, rows: &mut Vec<Vec<f32>>| -> Result<()> {
            let flat = to_f32(values, name, path)?;
            for (start, end) in offsets {
                rows.push(flat[start..end].to_vec());
            }
            Ok(())
        };
        match col.data_type() {
            DataType::List(_) => {
                let list = col.as_list::<i32>();
                let offsets = list.value_offsets();
                let base = offsets[0] as usize;
                let values = list.values().slice(base, offsets[list.len()] as usize - base);
                let mut spans = offsets.windows(2).map(|w| (w[0] as usize - base, w[1] as usize - base));
                per_row(&values, &mut spans, &mut rows)?;
            }
            DataType::LargeList(_) => {
                let list = col.as_list::<i64>();
                let offsets = list.value_offsets();
                let base = offsets[0] as usize;
                let values = list.values().slice(base, offsets[list.len()] as usize - base);
                let mut spans = offsets.windows(2).map(|w| (w[0] as usize - base, w[1] as usize - base));
                per_row(&values, &mut spans, &mut rows)?;
            }
            DataType::FixedSizeList(_, n) => {
                let list = col.as_fixed_size_list();
                let n = *n as usize;
                let values = list.values().slice(list.offset() * n, list.len() * n);
                let mut spans = (0..list.len()).map(|i| (i * n, (i + 1) * n));
                per_row(&values, &mut spans, &mut rows)?;
            }
            t if t.is_numeric() => {
                let mut spans = (0..col.len()).map(|i| (i, i + 1));
                per_row(col, &mut spans, &mut rows)?;
            }
            t => bail!("{}: column '{name}' holds {t}, expected a list of numbers", path.display()),
        }
    }
    Ok(rows)
}

fn to_f32(values: &ArrayRef, name: &str, path: &Path) -> Result<Vec<f32>> {
    ensure!(values.data_type().is_numeric(), "{}: column '{name}' holds {}, expected numbers", path.display(), values.data_type());
    if values.null_count() > 0 {
        return defect(DefectKind::NonFinite, format!("{}: column '{name}' holds null values", path.display()));
    }
    numbers(values, |v| v as f32, |v| v as f32, |v| v as f32).with_context(|| format!("{}: column '{name}' holds {}", path.display(), values.data_type()))
}

/// The values of a numeric array through `float` (floats), `signed` and `unsigned` (integers).
fn numbers<T>(a: &ArrayRef, float: impl Fn(f64) -> T, signed: impl Fn(i64) -> T, unsigned: impl Fn(u64) -> T) -> Result<Vec<T>> {
    macro_rules! each {
        ($ty:ty, $f:expr, $as:ty) => {
            if let Some(p) = a.as_primitive_opt::<$ty>() {
                return Ok(p.values().iter().map(|&v| $f(v as $as)).collect());
            }
        };
    }
    each!(Float32Type, float, f64);
    each!(Float64Type, float, f64);
    each!(Int8Type, signed, i64);
    each!(Int16Type, signed, i64);
    each!(Int32Type, signed, i64);
    each!(Int64Type, signed, i64);
    each!(UInt8Type, unsigned, u64);
    each!(UInt16Type, unsigned, u64);
    each!(UInt32Type, unsigned, u64);
    each!(UInt64Type, unsigned, u64);
    bail!("unsupported number type {}", a.data_type())
}

/// A scalar numeric column as f64 values.
pub fn floats(batches: &[RecordBatch], name: &str, path: &Path) -> Result<Vec<f64>> {
    let mut out = Vec::new();
    for batch in batches {
        let col = column(batch, name, path)?;
        ensure!(col.data_type().is_numeric(), "{}: column '{name}' holds {}, expected numbers", path.display(), col.data_type());
        ensure!(col.null_count() == 0, "{}: column '{name}' holds nulls", path.display());
        out.extend(numbers(col, |v| v, |v| v as f64, |v| v as f64).with_context(|| format!("{}: column '{name}'", path.display()))?);
    }
    Ok(out)
}

/// A scalar integer column as i64 values.
pub fn ints(batches: &[RecordBatch], name: &str, path: &Path) -> Result<Vec<i64>> {
    let mut out = Vec::new();
    for batch in batches {
        let col = column(batch, name, path)?;
        ensure!(col.data_type().is_integer(), "{}: column '{name}' holds {}, expected integers", path.display(), col.data_type());
        ensure!(col.null_count() == 0, "{}: column '{name}' holds nulls", path.display());
        let values = numbers(col, |_| None, Some, |v| i64::try_from(v).ok());
        let values = values.with_context(|| format!("{}: column '{name}'", path.display()))?;
        ensure!(values.iter().all(Option::is_some), "{}: column '{name}' holds integers beyond i64", path.display());
        out.extend(values.into_iter().flatten());
    }
    Ok(out)
}

/// An image column as Hugging Face `datasets.Image` stores it: per row a struct of `bytes` (the
/// encoded file) and `path`, or plain binary. Returns the bytes, or the path where there are none.
pub fn image_cells(batches: &[RecordBatch], name: &str, path: &Path) -> Result<Vec<ImageCell>> {
    let binary = |a: &ArrayRef, i: usize| -> Option<Vec<u8>> {
        if a.is_null(i) {
            return None;
        }
        match a.data_type() {
            DataType::Binary => Some(a.as_binary::<i32>().value(i).to_vec()),
            DataType::LargeBinary => Some(a.as_binary::<i64>().value(i).to_vec()),
            _ => None,
        }
    };
    let mut out = Vec::new();
    for batch in batches {
        let col = column(batch, name, path)?;
        match col.data_type() {
            DataType::Struct(_) => {
                let s = col.as_struct();
                let bytes = s.column_by_name("bytes");
                let paths = s.column_by_name("path");
                for i in 0..s.len() {
                    let b = bytes.and_then(|b| binary(b, i));
                    let p = paths.filter(|p| !p.is_null(i)).and_then(|p| match p.data_type() {
                        DataType::Utf8 => Some(p.as_string::<i32>().value(i).to_string()),
                        DataType::LargeUtf8 => Some(p.as_string::<i64>().value(i).to_string()),
                        _ => None,
                    });
                    out.push(match (b, p) {
                        (Some(b), _) if !b.is_empty() => ImageCell::Bytes(b),
                        (_, Some(p)) if !p.is_empty() => ImageCell::Path(p),
                        _ => return defect(DefectKind::Unreadable, format!("{}: column '{name}' row {} holds no image", path.display(), out.len())),
                    });
                }
            }
            DataType::Binary | DataType::LargeBinary => {
                for i in 0..col.len() {
                    match binary(col, i) {
                        Some(b) => out.push(ImageCell::Bytes(b)),
                        None => return defect(DefectKind::Unreadable, format!("{}: column '{name}' row {} holds no image", path.display(), out.len())),
                    }
                }
            }
            other => bail!("{}: column '{name}' holds {other}, expected images (struct of bytes and path, or binary)", path.display()),
        }
    }
    Ok(out)
}

/// One cell of an image column.
pub enum ImageCell {
    Bytes(Vec<u8>),
    /// A file, relative to the dataset root unless absolute.
    Path(String),
}

/// A list-of-strings column (or a plain string column, as 1-element lists).
pub fn string_lists(batches: &[RecordBatch], name: &str, path: &Path) -> Result<Vec<Vec<String>>> {
    let mut out = Vec::new();
    for batch in batches {
        let col = column(batch, name, path)?;
        let strings = |a: &ArrayRef| -> Result<Vec<String>> {
            let text = |i: usize, v: &dyn Fn(usize) -> String| if a.is_null(i) { String::new() } else { v(i) };
            Ok(match a.data_type() {
                DataType::Utf8 => (0..a.len()).map(|i| text(i, &|i| a.as_string::<i32>().value(i).to_string())).collect(),
                DataType::LargeUtf8 => (0..a.len()).map(|i| text(i, &|i| a.as_string::<i64>().value(i).to_string())).collect(),
                DataType::Utf8View => (0..a.len()).map(|i| text(i, &|i| a.as_string_view().value(i).to_string())).collect(),
                t => bail!("{}: column '{name}' holds {t}, expected text", path.display()),
            })
        };
        match col.data_type() {
            DataType::List(_) => {
                let list = col.as_list::<i32>();
                for i in 0..list.len() {
                    out.push(if list.is_null(i) { Vec::new() } else { strings(&list.value(i))? });
                }
            }
            DataType::LargeList(_) => {
                let list = col.as_list::<i64>();
                for i in 0..list.len() {
                    out.push(if list.is_null(i) { Vec::new() } else { strings(&list.value(i))? });
                }
            }
            _ => out.extend(strings(col)?.into_iter().map(|s| vec![s])),
        }
    }
    Ok(out)
}
