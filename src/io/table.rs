//! A small columnar table for outputs, and its Parquet reader and writers.
//!
//! [`Table`] holds named, equally long columns of `f64`, `i64`, `u64`, `bool` or `String`, which map
//! to the Arrow types float64, int64, uint64, boolean and utf8. [`write_parquet`] writes one table
//! atomically (Snappy compression); [`ParquetAppender`] streams many same-schema tables into one
//! file and renames it into place on [`ParquetAppender::finish`]. [`read_parquet`] reads any file
//! whose columns are float32/float64, (unsigned) integers, boolean or utf8 without nulls.

use std::fmt;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, AsArray, BooleanArray, Float64Array, Int64Array, RecordBatch, StringArray,
    UInt64Array,
};
use arrow::datatypes::{
    DataType, Field, Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type, Schema,
    SchemaRef, UInt16Type, UInt32Type, UInt64Type, UInt8Type,
};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;

use super::atomic::AtomicFile;
use super::{in_memory, IoError, DEBUG_MAX_ROWS};

/// Rows per record batch when reading.
const READ_BATCH_ROWS: usize = 64 * 1024;

/// One column of a [`Table`].
#[derive(Debug, Clone, PartialEq)]
pub enum Column {
    F64(Vec<f64>),
    I64(Vec<i64>),
    U64(Vec<u64>),
    Bool(Vec<bool>),
    Str(Vec<String>),
}

impl Column {
    /// Number of rows.
    pub fn len(&self) -> usize {
        match self {
            Column::F64(v) => v.len(),
            Column::I64(v) => v.len(),
            Column::U64(v) => v.len(),
            Column::Bool(v) => v.len(),
            Column::Str(v) => v.len(),
        }
    }

    /// True if the column has no rows.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The Arrow type name: `float64`, `int64`, `uint64`, `boolean` or `utf8`.
    pub fn type_name(&self) -> &'static str {
        match self {
            Column::F64(_) => "float64",
            Column::I64(_) => "int64",
            Column::U64(_) => "uint64",
            Column::Bool(_) => "boolean",
            Column::Str(_) => "utf8",
        }
    }

    /// The values as `f64` for numeric columns (integers are converted, exactly up to 2^53);
    /// `None` for boolean and string columns.
    pub fn to_f64(&self) -> Option<Vec<f64>> {
        match self {
            Column::F64(v) => Some(v.clone()),
            Column::I64(v) => Some(v.iter().map(|&x| x as f64).collect()),
            Column::U64(v) => Some(v.iter().map(|&x| x as f64).collect()),
            Column::Bool(_) | Column::Str(_) => None,
        }
    }

    fn empty_like(&self) -> Column {
        match self {
            Column::F64(_) => Column::F64(Vec::new()),
            Column::I64(_) => Column::I64(Vec::new()),
            Column::U64(_) => Column::U64(Vec::new()),
            Column::Bool(_) => Column::Bool(Vec::new()),
            Column::Str(_) => Column::Str(Vec::new()),
        }
    }

    /// Appends `other`, which must have the same type (checked by the caller).
    fn extend_from(&mut self, other: &Column) -> bool {
        match (self, other) {
            (Column::F64(a), Column::F64(b)) => a.extend_from_slice(b),
            (Column::I64(a), Column::I64(b)) => a.extend_from_slice(b),
            (Column::U64(a), Column::U64(b)) => a.extend_from_slice(b),
            (Column::Bool(a), Column::Bool(b)) => a.extend_from_slice(b),
            (Column::Str(a), Column::Str(b)) => a.extend_from_slice(b),
            _ => return false,
        }
        true
    }

    fn data_type(&self) -> DataType {
        match self {
            Column::F64(_) => DataType::Float64,
            Column::I64(_) => DataType::Int64,
            Column::U64(_) => DataType::UInt64,
            Column::Bool(_) => DataType::Boolean,
            Column::Str(_) => DataType::Utf8,
        }
    }

    fn to_arrow(&self) -> ArrayRef {
        match self {
            Column::F64(v) => Arc::new(Float64Array::from(v.clone())),
            Column::I64(v) => Arc::new(Int64Array::from(v.clone())),
            Column::U64(v) => Arc::new(UInt64Array::from(v.clone())),
            Column::Bool(v) => Arc::new(BooleanArray::from(v.clone())),
            Column::Str(v) => Arc::new(StringArray::from_iter_values(v.iter())),
        }
    }
}

impl From<Vec<f64>> for Column {
    fn from(v: Vec<f64>) -> Self {
        Column::F64(v)
    }
}
impl From<Vec<i64>> for Column {
    fn from(v: Vec<i64>) -> Self {
        Column::I64(v)
    }
}
impl From<Vec<u64>> for Column {
    fn from(v: Vec<u64>) -> Self {
        Column::U64(v)
    }
}
impl From<Vec<bool>> for Column {
    fn from(v: Vec<bool>) -> Self {
        Column::Bool(v)
    }
}
impl From<Vec<String>> for Column {
    fn from(v: Vec<String>) -> Self {
        Column::Str(v)
    }
}

/// Named columns of equal length. `source` is the file it was read from, if any, and names that
/// file in error messages.
#[derive(Clone, PartialEq, Default)]
pub struct Table {
    pub columns: Vec<(String, Column)>,
    pub source: Option<PathBuf>,
}

/// Summarises long tables instead of printing every value.
impl fmt::Debug for Table {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut d = f.debug_struct("Table");
        d.field("source", &self.source)
            .field("rows", &self.num_rows());
        if self.num_rows() <= DEBUG_MAX_ROWS {
            d.field("columns", &self.columns);
        } else {
            let summary: Vec<String> = self
                .columns
                .iter()
                .map(|(n, c)| format!("{n}: {}", c.type_name()))
                .collect();
            d.field("columns", &summary);
        }
        d.finish()
    }
}

impl Table {
    /// An empty table (no columns).
    pub fn new() -> Table {
        Table::default()
    }

    /// Sets the file named in error messages.
    pub fn with_source(mut self, path: impl Into<PathBuf>) -> Table {
        self.source = Some(path.into());
        self
    }

    /// The file this table came from, if any.
    pub fn source(&self) -> Option<&Path> {
        self.source.as_deref()
    }

    /// Adds a column; errors if the name is taken or the length differs from the existing columns.
    pub fn with_column(
        mut self,
        name: impl Into<String>,
        column: impl Into<Column>,
    ) -> Result<Table, IoError> {
        self.push_column(name, column)?;
        Ok(self)
    }

    /// Adds a `float64` column.
    pub fn with_f64(self, name: impl Into<String>, values: Vec<f64>) -> Result<Table, IoError> {
        self.with_column(name, Column::F64(values))
    }

    /// Adds an `int64` column.
    pub fn with_i64(self, name: impl Into<String>, values: Vec<i64>) -> Result<Table, IoError> {
        self.with_column(name, Column::I64(values))
    }

    /// Adds a `uint64` column.
    pub fn with_u64(self, name: impl Into<String>, values: Vec<u64>) -> Result<Table, IoError> {
        self.with_column(name, Column::U64(values))
    }

    /// Adds a `boolean` column.
    pub fn with_bool(self, name: impl Into<String>, values: Vec<bool>) -> Result<Table, IoError> {
        self.with_column(name, Column::Bool(values))
    }

    /// Adds a `utf8` column.
    pub fn with_str<S: Into<String>>(
        self,
        name: impl Into<String>,
        values: impl IntoIterator<Item = S>,
    ) -> Result<Table, IoError> {
        let values = values.into_iter().map(Into::into).collect();
        self.with_column(name, Column::Str(values))
    }

    /// Adds a column in place; same checks as [`Table::with_column`].
    pub fn push_column(
        &mut self,
        name: impl Into<String>,
        column: impl Into<Column>,
    ) -> Result<(), IoError> {
        let name = name.into();
        let column = column.into();
        if self.columns.iter().any(|(n, _)| *n == name) {
            return Err(IoError::DuplicateColumn {
                path: self.label(),
                column: name,
            });
        }
        if let Some((_, first)) = self.columns.first() {
            if first.len() != column.len() {
                return Err(IoError::ColumnLength {
                    path: self.label(),
                    column: name,
                    len: column.len(),
                    expected: first.len(),
                });
            }
        }
        self.columns.push((name, column));
        Ok(())
    }

    /// Number of rows (0 for a table without columns).
    pub fn num_rows(&self) -> usize {
        self.columns.first().map_or(0, |(_, c)| c.len())
    }

    /// Number of columns.
    pub fn num_columns(&self) -> usize {
        self.columns.len()
    }

    /// True if the table has no rows.
    pub fn is_empty(&self) -> bool {
        self.num_rows() == 0
    }

    /// Column names, in order.
    pub fn names(&self) -> Vec<&str> {
        self.columns.iter().map(|(n, _)| n.as_str()).collect()
    }

    /// The column called `name`; the error names the source file and lists the columns found.
    pub fn column(&self, name: &str) -> Result<&Column, IoError> {
        self.columns
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, c)| c)
            .ok_or_else(|| IoError::MissingColumn {
                path: self.label(),
                column: name.to_string(),
                found: self.names().iter().map(|s| s.to_string()).collect(),
            })
    }

    /// The `float64` column called `name`.
    pub fn f64_column(&self, name: &str) -> Result<&[f64], IoError> {
        match self.column(name)? {
            Column::F64(v) => Ok(v),
            other => Err(self.type_error(name, "float64", other)),
        }
    }

    /// The `int64` column called `name`.
    pub fn i64_column(&self, name: &str) -> Result<&[i64], IoError> {
        match self.column(name)? {
            Column::I64(v) => Ok(v),
            other => Err(self.type_error(name, "int64", other)),
        }
    }

    /// The `uint64` column called `name`.
    pub fn u64_column(&self, name: &str) -> Result<&[u64], IoError> {
        match self.column(name)? {
            Column::U64(v) => Ok(v),
            other => Err(self.type_error(name, "uint64", other)),
        }
    }

    /// The `boolean` column called `name`.
    pub fn bool_column(&self, name: &str) -> Result<&[bool], IoError> {
        match self.column(name)? {
            Column::Bool(v) => Ok(v),
            other => Err(self.type_error(name, "boolean", other)),
        }
    }

    /// The `utf8` column called `name`.
    pub fn str_column(&self, name: &str) -> Result<&[String], IoError> {
        match self.column(name)? {
            Column::Str(v) => Ok(v),
            other => Err(self.type_error(name, "utf8", other)),
        }
    }

    /// The numeric column called `name` converted to `f64`.
    pub fn column_as_f64(&self, name: &str) -> Result<Vec<f64>, IoError> {
        let column = self.column(name)?;
        column
            .to_f64()
            .ok_or_else(|| self.type_error(name, "a numeric type", column))
    }

    /// Appends the rows of `other`, which must have the same column names and types in the same
    /// order.
    pub fn append(&mut self, other: &Table) -> Result<(), IoError> {
        check_same_schema(&self.label(), self, other)?;
        for ((_, a), (_, b)) in self.columns.iter_mut().zip(&other.columns) {
            a.extend_from(b);
        }
        Ok(())
    }

    /// Checks that names are unique and all columns have the same length (the fields are public,
    /// so a table built by hand may violate this).
    pub fn validate(&self) -> Result<(), IoError> {
        let rows = self.num_rows();
        for (i, (name, column)) in self.columns.iter().enumerate() {
            if self.columns[..i].iter().any(|(n, _)| n == name) {
                return Err(IoError::DuplicateColumn {
                    path: self.label(),
                    column: name.clone(),
                });
            }
            if column.len() != rows {
                return Err(IoError::ColumnLength {
                    path: self.label(),
                    column: name.clone(),
                    len: column.len(),
                    expected: rows,
                });
            }
        }
        Ok(())
    }

    /// The source path, or `<table>` for messages about an in-memory table.
    fn label(&self) -> PathBuf {
        self.source.clone().unwrap_or_else(|| in_memory("table"))
    }

    fn type_error(&self, name: &str, expected: &str, found: &Column) -> IoError {
        IoError::ColumnType {
            path: self.label(),
            column: name.to_string(),
            expected: expected.to_string(),
            found: found.type_name().to_string(),
        }
    }

    fn arrow_schema(&self) -> SchemaRef {
        Arc::new(Schema::new(
            self.columns
                .iter()
                .map(|(n, c)| Field::new(n, c.data_type(), false))
                .collect::<Vec<_>>(),
        ))
    }

    fn to_record_batch(&self, schema: SchemaRef, path: &Path) -> Result<RecordBatch, IoError> {
        let arrays = self.columns.iter().map(|(_, c)| c.to_arrow()).collect();
        RecordBatch::try_new(schema, arrays)
            .map_err(|e| IoError::invalid(path, format!("cannot build record batch: {e}")))
    }
}

/// Errors unless `b` has the column names and types of `a`, in the same order.
fn check_same_schema(path: &Path, a: &Table, b: &Table) -> Result<(), IoError> {
    let describe = |t: &Table| {
        t.columns
            .iter()
            .map(|(n, c)| format!("{n}: {}", c.type_name()))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let same = a.columns.len() == b.columns.len()
        && a.columns
            .iter()
            .zip(&b.columns)
            .all(|((na, ca), (nb, cb))| na == nb && ca.type_name() == cb.type_name());
    if same {
        Ok(())
    } else {
        Err(IoError::invalid(
            path,
            format!(
                "schema mismatch: expected columns [{}], got [{}]",
                describe(a),
                describe(b)
            ),
        ))
    }
}

fn writer_properties() -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .build()
}

fn parquet_write_error(path: &Path, e: parquet::errors::ParquetError) -> IoError {
    let error = match e {
        parquet::errors::ParquetError::External(inner) => {
            match inner.downcast::<std::io::Error>() {
                Ok(io) => *io,
                Err(other) => std::io::Error::other(other.to_string()),
            }
        }
        other => std::io::Error::other(other.to_string()),
    };
    IoError::write(path, error)
}

/// Writes `table` to `path` as Snappy-compressed Parquet, atomically.
pub fn write_parquet(path: impl AsRef<Path>, table: &Table) -> Result<(), IoError> {
    let path = path.as_ref();
    let mut appender = ParquetAppender::create(path)?;
    appender.append(table)?;
    appender.finish()
}

/// Streams same-schema [`Table`]s into one Parquet file, written to a temporary file and renamed
/// into place by [`finish`](ParquetAppender::finish). Dropping the appender unfinished removes the
/// temporary file and leaves the destination untouched.
pub struct ParquetAppender {
    dest: PathBuf,
    /// Until the first batch fixes the schema the file is held here.
    pending: Option<AtomicFile>,
    writer: Option<ArrowWriter<AtomicFile>>,
    /// First batch's columns with no rows: the schema later batches must match.
    schema: Option<Table>,
    arrow_schema: Option<SchemaRef>,
    rows: usize,
    batches: usize,
}

impl ParquetAppender {
    /// Creates the temporary file next to `path` (so an unwritable directory fails here).
    pub fn create(path: impl AsRef<Path>) -> Result<ParquetAppender, IoError> {
        let dest = path.as_ref().to_path_buf();
        let file = AtomicFile::create(&dest)?;
        Ok(ParquetAppender {
            dest,
            pending: Some(file),
            writer: None,
            schema: None,
            arrow_schema: None,
            rows: 0,
            batches: 0,
        })
    }

    /// The destination path.
    pub fn path(&self) -> &Path {
        &self.dest
    }

    /// Rows appended so far.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Batches appended so far.
    pub fn batches(&self) -> usize {
        self.batches
    }

    /// Appends the rows of `batch`. The first batch fixes the schema; later ones must have the
    /// same column names and types in the same order.
    pub fn append(&mut self, batch: &Table) -> Result<(), IoError> {
        batch.validate()?;
        if batch.columns.is_empty() {
            return Err(IoError::invalid(
                &self.dest,
                "cannot write a table without columns",
            ));
        }
        if let Some(schema) = &self.schema {
            check_same_schema(&self.dest, schema, batch).map_err(|e| match e {
                IoError::Invalid { path, message } => IoError::Invalid {
                    path,
                    message: format!("batch {}: {message}", self.batches),
                },
                other => other,
            })?;
        } else {
            let file = self
                .pending
                .take()
                .ok_or_else(|| IoError::invalid(&self.dest, "appender already finished"))?;
            let arrow_schema = batch.arrow_schema();
            let writer =
                ArrowWriter::try_new(file, arrow_schema.clone(), Some(writer_properties()))
                    .map_err(|e| parquet_write_error(&self.dest, e))?;
            self.writer = Some(writer);
            self.arrow_schema = Some(arrow_schema);
            self.schema = Some(Table {
                columns: batch
                    .columns
                    .iter()
                    .map(|(n, c)| (n.clone(), c.empty_like()))
                    .collect(),
                source: None,
            });
        }
        let schema = self.arrow_schema.clone().expect("schema set above");
        let record_batch = batch.to_record_batch(schema, &self.dest)?;
        let writer = self
            .writer
            .as_mut()
            .ok_or_else(|| IoError::invalid(&self.dest, "appender already finished"))?;
        writer
            .write(&record_batch)
            .map_err(|e| parquet_write_error(&self.dest, e))?;
        self.rows += batch.num_rows();
        self.batches += 1;
        Ok(())
    }

    /// Writes the footer, syncs and renames the file into place. Errors if nothing was appended
    /// (a Parquet file needs a schema).
    pub fn finish(mut self) -> Result<(), IoError> {
        let writer = self.writer.take().ok_or_else(|| {
            IoError::invalid(&self.dest, "nothing to write: no batch was appended")
        })?;
        let file = writer
            .into_inner()
            .map_err(|e| parquet_write_error(&self.dest, e))?;
        file.commit()
    }
}

/// Reads a Parquet file into a [`Table`] whose `source` is `path`.
///
/// float32 and float64 become [`Column::F64`]; int8..int64 [`Column::I64`]; uint8..uint64
/// [`Column::U64`]; boolean [`Column::Bool`]; utf8 and large utf8 [`Column::Str`]. Other types and
/// null values are errors naming the column (and row).
pub fn read_parquet(path: impl AsRef<Path>) -> Result<Table, IoError> {
    let path = path.as_ref();
    let file = File::open(path).map_err(|e| IoError::read(path, e))?;
    let parquet_err = |e: parquet::errors::ParquetError| match e {
        parquet::errors::ParquetError::External(inner) => {
            match inner.downcast::<std::io::Error>() {
                Ok(io) => IoError::read(path, *io),
                Err(other) => IoError::Parquet {
                    path: path.to_path_buf(),
                    message: other.to_string(),
                },
            }
        }
        other => IoError::Parquet {
            path: path.to_path_buf(),
            message: other.to_string(),
        },
    };
    let builder = ParquetRecordBatchReaderBuilder::try_new(file).map_err(parquet_err)?;
    let schema = builder.schema().clone();

    let mut table = Table {
        columns: Vec::with_capacity(schema.fields().len()),
        source: Some(path.to_path_buf()),
    };
    for field in schema.fields() {
        let column = empty_column_for(field.data_type()).ok_or_else(|| IoError::ColumnType {
            path: path.to_path_buf(),
            column: field.name().clone(),
            expected: "float32, float64, (unsigned) integer, boolean or utf8".to_string(),
            found: field.data_type().to_string(),
        })?;
        if table.columns.iter().any(|(n, _)| n == field.name()) {
            return Err(IoError::DuplicateColumn {
                path: path.to_path_buf(),
                column: field.name().clone(),
            });
        }
        table.columns.push((field.name().clone(), column));
    }

    let reader = builder
        .with_batch_size(READ_BATCH_ROWS)
        .build()
        .map_err(parquet_err)?;
    let mut row0 = 0;
    for batch in reader {
        let batch = batch.map_err(|e| IoError::Parquet {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        for ((name, column), array) in table.columns.iter_mut().zip(batch.columns()) {
            if array.null_count() > 0 {
                let row = (0..array.len()).find(|&i| array.is_null(i)).unwrap_or(0);
                return Err(IoError::NullValue {
                    path: path.to_path_buf(),
                    column: name.clone(),
                    row: row0 + row,
                });
            }
            extend_from_arrow(column, array.as_ref());
        }
        row0 += batch.num_rows();
    }
    Ok(table)
}

fn empty_column_for(dt: &DataType) -> Option<Column> {
    Some(match dt {
        DataType::Float32 | DataType::Float64 => Column::F64(Vec::new()),
        DataType::Int8 | DataType::Int16 | DataType::Int32 | DataType::Int64 => {
            Column::I64(Vec::new())
        }
        DataType::UInt8 | DataType::UInt16 | DataType::UInt32 | DataType::UInt64 => {
            Column::U64(Vec::new())
        }
        DataType::Boolean => Column::Bool(Vec::new()),
        DataType::Utf8 | DataType::LargeUtf8 => Column::Str(Vec::new()),
        _ => return None,
    })
}

/// Appends a null-free Arrow array of a type accepted by [`empty_column_for`].
fn extend_from_arrow(column: &mut Column, array: &dyn Array) {
    match (column, array.data_type()) {
        (Column::F64(v), DataType::Float64) => {
            v.extend_from_slice(array.as_primitive::<Float64Type>().values())
        }
        (Column::F64(v), DataType::Float32) => v.extend(
            array
                .as_primitive::<Float32Type>()
                .values()
                .iter()
                .map(|&x| f64::from(x)),
        ),
        (Column::I64(v), DataType::Int64) => {
            v.extend_from_slice(array.as_primitive::<Int64Type>().values())
        }
        (Column::I64(v), DataType::Int32) => v.extend(
            array
                .as_primitive::<Int32Type>()
                .values()
                .iter()
                .map(|&x| i64::from(x)),
        ),
        (Column::I64(v), DataType::Int16) => v.extend(
            array
                .as_primitive::<Int16Type>()
                .values()
                .iter()
                .map(|&x| i64::from(x)),
        ),
        (Column::I64(v), DataType::Int8) => v.extend(
            array
                .as_primitive::<Int8Type>()
                .values()
                .iter()
                .map(|&x| i64::from(x)),
        ),
        (Column::U64(v), DataType::UInt64) => {
            v.extend_from_slice(array.as_primitive::<UInt64Type>().values())
        }
        (Column::U64(v), DataType::UInt32) => v.extend(
            array
                .as_primitive::<UInt32Type>()
                .values()
                .iter()
                .map(|&x| u64::from(x)),
        ),
        (Column::U64(v), DataType::UInt16) => v.extend(
            array
                .as_primitive::<UInt16Type>()
                .values()
                .iter()
                .map(|&x| u64::from(x)),
        ),
        (Column::U64(v), DataType::UInt8) => v.extend(
            array
                .as_primitive::<UInt8Type>()
                .values()
                .iter()
                .map(|&x| u64::from(x)),
        ),
        (Column::Bool(v), DataType::Boolean) => v.extend(array.as_boolean().values().iter()),
        (Column::Str(v), DataType::Utf8) => v.extend(
            array
                .as_string::<i32>()
                .iter()
                .map(|s| s.unwrap_or_default().to_string()),
        ),
        (Column::Str(v), DataType::LargeUtf8) => v.extend(
            array
                .as_string::<i64>()
                .iter()
                .map(|s| s.unwrap_or_default().to_string()),
        ),
        (column, dt) => unreachable!("column {} cannot take {dt}", column.type_name()),
    }
}
