//! A small columnar table for outputs, and its Parquet reader and writers.
//!
//! [`Table`] holds named, equally long columns of `f64`, `i64`, `u64`, `bool` or `String`, which map
//! to the Arrow types float64, int64, uint64, boolean and utf8. [`write_parquet`] writes one table
//! atomically (Snappy compression); [`ParquetAppender`] streams many same-schema tables into one
//! file and renames it into place on [`ParquetAppender::finish`]. [`read_parquet`] reads any file
//! whose columns are float32/float64, (unsigned) integers, boolean or utf8 without nulls.
//!
//! Written tables describe themselves: the Parquet key-value metadata carries
//! `freefall.version` ([`crate::VERSION`]: crate version, git commit, build profile), whatever the caller added with [`Table::with_meta`]
//! (model, dataset and campaign hashes) and `freefall.units`, a JSON object of the units set with
//! [`Table::with_unit`] (`{}` when there are none); each field's Arrow metadata carries its
//! `unit` too. The same key-value pairs are in the Arrow schema and in the Parquet footer's
//! key-value metadata. Columns marked with
//! [`Table::with_nan_as_null`] store NaN (a value that does not exist, such as a whitened
//! residual inside the filter's start-up) as a Parquet null.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fmt;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, AsArray, BooleanArray, Float64Array, Int64Array, RecordBatch, StringArray,
    UInt64Array,
};
use arrow::datatypes::{
    ArrowPrimitiveType, DataType, Field, Float32Type, Float64Type, Int16Type, Int32Type, Int64Type,
    Int8Type, Schema, SchemaRef, TimeUnit, UInt16Type, UInt32Type, UInt64Type, UInt8Type,
};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::metadata::KeyValue;
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
    /// Key-value metadata written with the table (besides `freefall.version` and the units).
    pub meta: BTreeMap<String, String>,
    /// Unit of each column that has one (SI symbols, `1` for dimensionless).
    pub units: BTreeMap<String, String>,
    /// `f64` columns whose NaN values are written as nulls.
    pub nan_as_null: BTreeSet<String>,
}

/// Key of the crate version in every written table's metadata.
pub const VERSION_KEY: &str = "freefall.version";
/// Key of the JSON object of column units in every written table's metadata.
pub const UNITS_KEY: &str = "freefall.units";
/// Key of a column's unit in its Arrow field metadata.
pub const FIELD_UNIT_KEY: &str = "unit";

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

    /// Adds a key-value pair to the metadata written with the table.
    pub fn with_meta(mut self, key: impl Into<String>, value: impl Into<String>) -> Table {
        self.meta.insert(key.into(), value.into());
        self
    }

    /// Adds every pair of `meta` to the metadata written with the table.
    pub fn with_meta_all(mut self, meta: &BTreeMap<String, String>) -> Table {
        self.meta
            .extend(meta.iter().map(|(k, v)| (k.clone(), v.clone())));
        self
    }

    /// Sets the unit of column `name` (written in the field's metadata and in `freefall.units`).
    pub fn with_unit(mut self, name: impl Into<String>, unit: impl Into<String>) -> Table {
        self.units.insert(name.into(), unit.into());
        self
    }

    /// Sets the units of several columns.
    pub fn with_units<N: Into<String>, U: Into<String>>(
        mut self,
        units: impl IntoIterator<Item = (N, U)>,
    ) -> Table {
        for (n, u) in units {
            self.units.insert(n.into(), u.into());
        }
        self
    }

    /// Writes the NaN values of `f64` column `name` as nulls (missing values, not numbers).
    pub fn with_nan_as_null(mut self, name: impl Into<String>) -> Table {
        self.nan_as_null.insert(name.into());
        self
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

    /// A count column (`int64`, or `uint64` as tables before 0.1 wrote counts) as `u64`; a
    /// negative value is an error naming the column and row.
    pub fn count_column(&self, name: &str) -> Result<Vec<u64>, IoError> {
        match self.column(name)? {
            Column::U64(v) => Ok(v.clone()),
            Column::I64(v) => v
                .iter()
                .enumerate()
                .map(|(row, &x)| {
                    u64::try_from(x).map_err(|_| {
                        IoError::invalid(
                            &self.label(),
                            format!("column '{name}' row {row}: negative count {x}"),
                        )
                    })
                })
                .collect(),
            other => Err(self.type_error(name, "int64", other)),
        }
    }

    /// Adds an `int64` column of counts (every integer column freefall writes is `int64`, the
    /// type pandas, polars and DuckDB default to).
    pub fn with_counts(self, name: impl Into<String>, values: &[u64]) -> Result<Table, IoError> {
        let v = values
            .iter()
            .map(|&x| i64::try_from(x).unwrap_or(i64::MAX))
            .collect();
        self.with_column(name, Column::I64(v))
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
        let fields: Vec<Field> = self
            .columns
            .iter()
            .map(|(n, c)| {
                let field = Field::new(n, c.data_type(), self.nan_as_null.contains(n));
                match self.units.get(n) {
                    Some(u) => field
                        .with_metadata(HashMap::from([(FIELD_UNIT_KEY.to_string(), u.clone())])),
                    None => field,
                }
            })
            .collect();
        let mut meta: HashMap<String, String> = self
            .meta
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        meta.insert(VERSION_KEY.into(), crate::VERSION.into());
        let units: BTreeMap<&str, &str> = self
            .columns
            .iter()
            .filter_map(|(n, _)| Some((n.as_str(), self.units.get(n)?.as_str())))
            .collect();
        // Always present, `{}` when no column has one unit (tables whose rows mix parameters
        // carry a `unit` column instead), so a reader can rely on the key.
        meta.insert(
            UNITS_KEY.into(),
            serde_json::to_string(&units).expect("a map of strings serialises"),
        );
        Arc::new(Schema::new_with_metadata(fields, meta))
    }

    fn to_record_batch(&self, schema: SchemaRef, path: &Path) -> Result<RecordBatch, IoError> {
        let arrays = self
            .columns
            .iter()
            .map(|(n, c)| match c {
                Column::F64(v) if self.nan_as_null.contains(n) => Arc::new(
                    v.iter()
                        .map(|x| (!x.is_nan()).then_some(*x))
                        .collect::<Float64Array>(),
                ) as ArrayRef,
                c => c.to_arrow(),
            })
            .collect();
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

/// Snappy compression, and the schema's metadata (`freefall.version`, `freefall.units`, the
/// hashes) copied into the Parquet footer's key-value metadata, sorted by key, where readers
/// that do not decode the Arrow schema (DuckDB's `parquet_kv_metadata()`, polars'
/// `read_parquet_metadata()`) find it. The writer adds `ARROW:schema` after these.
/// The estimated encoded size at which a Parquet file's row group is closed and written out.
/// The writer holds the open row group in memory, so this bounds what a long stream of batches
/// (a campaign's `realizations.parquet` of 10^5 rows and more) costs, instead of the default
/// million rows; the values read back are the same for any row-group layout.
pub const ROW_GROUP_BYTES: usize = 1 << 20;

fn writer_properties(schema: &Schema) -> WriterProperties {
    let kv: Vec<KeyValue> = schema
        .metadata()
        .iter()
        .collect::<BTreeMap<_, _>>()
        .into_iter()
        .map(|(k, v)| KeyValue::new(k.clone(), v.clone()))
        .collect();
    WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_max_row_group_bytes(Some(ROW_GROUP_BYTES))
        .set_key_value_metadata(Some(kv))
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
            let writer = ArrowWriter::try_new(
                file,
                arrow_schema.clone(),
                Some(writer_properties(&arrow_schema)),
            )
            .map_err(|e| parquet_write_error(&self.dest, e))?;
            self.writer = Some(writer);
            self.arrow_schema = Some(arrow_schema);
            self.schema = Some(Table {
                columns: batch
                    .columns
                    .iter()
                    .map(|(n, c)| (n.clone(), c.empty_like()))
                    .collect(),
                nan_as_null: batch.nan_as_null.clone(),
                ..Table::default()
            });
        }
        let schema = self.arrow_schema.clone().expect("schema set above");
        // Nulls follow the first batch's marking, whatever later batches say.
        let record_batch = match &self.schema {
            Some(first) if first.nan_as_null != batch.nan_as_null => Table {
                nan_as_null: first.nan_as_null.clone(),
                ..batch.clone()
            }
            .to_record_batch(schema, &self.dest)?,
            _ => batch.to_record_batch(schema, &self.dest)?,
        };
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
/// [`Column::U64`]; boolean [`Column::Bool`]; utf8 and large utf8 [`Column::Str`]; Arrow
/// timestamps [`Column::I64`] nanoseconds since the Unix epoch. Other types and null values are
/// errors naming the column (and row).
pub fn read_parquet(path: impl AsRef<Path>) -> Result<Table, IoError> {
    read_parquet_with(path.as_ref(), None, NullsAsNan::None).map(|(t, _)| t)
}

/// Like [`read_parquet`], but nulls in float columns (missing values, as freefall writes them
/// with [`Table::with_nan_as_null`]) read as NaN, and those columns are marked to write back as
/// nulls. Nulls in other columns are still errors.
pub fn read_parquet_nulls_as_nan(path: impl AsRef<Path>) -> Result<Table, IoError> {
    read_parquet_with(path.as_ref(), None, NullsAsNan::All).map(|(t, _)| t)
}

/// What [`read_parquet_tolerant`] did besides reading: columns it left out and why, and the
/// columns stored with less than float64 precision or as timestamps.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReadReport {
    /// `(column, reason)` of every column left out.
    pub skipped: Vec<(String, String)>,
    /// float32 columns (7 significant digits), read as float64.
    pub float32: Vec<String>,
    /// Timestamp columns, read as int64 nanoseconds since the Unix epoch.
    pub timestamps: Vec<String>,
}

/// Like [`read_parquet`], but a column not in `required` whose type freefall cannot read (a
/// dictionary-encoded flag, a struct) or that holds a null is left out and reported instead of
/// failing the file. Required columns get the strict checks.
pub fn read_parquet_tolerant(
    path: impl AsRef<Path>,
    required: &[&str],
) -> Result<(Table, ReadReport), IoError> {
    read_parquet_with(path.as_ref(), Some(required), NullsAsNan::None)
}

/// [`read_parquet_tolerant`], but nulls in the float columns named in `missing` (samples that
/// were not recorded) read as NaN, and those columns are listed in the table's `nan_as_null`.
/// Nulls elsewhere are treated as by [`read_parquet_tolerant`].
pub fn read_parquet_tolerant_missing(
    path: impl AsRef<Path>,
    required: &[&str],
    missing: &[&str],
) -> Result<(Table, ReadReport), IoError> {
    read_parquet_with(path.as_ref(), Some(required), NullsAsNan::Only(missing))
}

/// Which float columns read a null as NaN.
#[derive(Clone, Copy)]
enum NullsAsNan<'a> {
    None,
    All,
    Only(&'a [&'a str]),
}

impl NullsAsNan<'_> {
    fn applies(&self, name: &str) -> bool {
        match self {
            NullsAsNan::None => false,
            NullsAsNan::All => true,
            NullsAsNan::Only(names) => names.contains(&name),
        }
    }
}

/// The reader: strict when `required` is `None`, else tolerant of the other columns. A
/// corrupt file can make the parquet crate's decoder panic (seen: "column start and length
/// should not be negative" on a file with mutated page headers, by the fuzz test of
/// tests/it/hostile.rs); the panic is caught and reported as an error naming the file.
fn read_parquet_with(
    path: &Path,
    required: Option<&[&str]>,
    float_nulls_as_nan: NullsAsNan,
) -> Result<(Table, ReadReport), IoError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        read_parquet_unguarded(path, required, float_nulls_as_nan)
    }))
    .unwrap_or_else(|payload| {
        let why = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown".into());
        Err(IoError::Parquet {
            path: path.to_path_buf(),
            message: format!("corrupt file: the Parquet decoder failed ({why})"),
        })
    })
}

fn read_parquet_unguarded(
    path: &Path,
    required: Option<&[&str]>,
    float_nulls_as_nan: NullsAsNan,
) -> Result<(Table, ReadReport), IoError> {
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
    let strict = |name: &str| required.is_none_or(|r| r.contains(&name));
    let builder = ParquetRecordBatchReaderBuilder::try_new(file).map_err(parquet_err)?;
    let schema = builder.schema().clone();
    let mut report = ReadReport::default();
    let mut table = Table {
        columns: Vec::with_capacity(schema.fields().len()),
        source: Some(path.to_path_buf()),
        meta: schema
            .metadata()
            .iter()
            .filter(|(k, _)| k.as_str() != UNITS_KEY)
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect(),
        units: schema
            .fields()
            .iter()
            .filter_map(|f| Some((f.name().clone(), f.metadata().get(FIELD_UNIT_KEY)?.clone())))
            .collect(),
        nan_as_null: BTreeSet::new(),
    };
    // Index into the file's columns of every kept column.
    let mut kept: Vec<usize> = Vec::new();
    for (i, field) in schema.fields().iter().enumerate() {
        let Some(column) = empty_column_for(field.data_type()) else {
            if strict(field.name()) {
                return Err(IoError::ColumnType {
                    path: path.to_path_buf(),
                    column: field.name().clone(),
                    expected: "float32, float64, (unsigned) integer, timestamp, boolean or utf8"
                        .to_string(),
                    found: field.data_type().to_string(),
                });
            }
            report
                .skipped
                .push((field.name().clone(), format!("type {}", field.data_type())));
            continue;
        };
        if table.columns.iter().any(|(n, _)| n == field.name()) {
            return Err(IoError::DuplicateColumn {
                path: path.to_path_buf(),
                column: field.name().clone(),
            });
        }
        match field.data_type() {
            DataType::Float32 => report.float32.push(field.name().clone()),
            DataType::Timestamp(..) => report.timestamps.push(field.name().clone()),
            _ => {}
        }
        table.columns.push((field.name().clone(), column));
        kept.push(i);
    }

    let reader = builder
        .with_batch_size(READ_BATCH_ROWS)
        .build()
        .map_err(parquet_err)?;
    let mut row0 = 0;
    let mut dropped: Vec<usize> = Vec::new();
    for batch in reader {
        let batch = batch.map_err(|e| IoError::Parquet {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        for (k, &i) in kept.iter().enumerate() {
            let (name, column) = &mut table.columns[k];
            let array = batch.column(i);
            if dropped.contains(&k) {
                continue;
            }
            if array.null_count() > 0
                && float_nulls_as_nan.applies(name)
                && matches!(column, Column::F64(_))
            {
                let floats = arrow::compute::cast(array, &DataType::Float64)
                    .expect("a float32 or float64 column casts to float64");
                if let Column::F64(v) = column {
                    let f = floats.as_primitive::<Float64Type>();
                    v.extend(
                        (0..f.len()).map(|r| if f.is_null(r) { f64::NAN } else { f.value(r) }),
                    );
                }
                table.nan_as_null.insert(name.clone());
                continue;
            }
            if array.null_count() > 0 {
                let row = row0 + (0..array.len()).find(|&r| array.is_null(r)).unwrap_or(0);
                if strict(name) {
                    return Err(IoError::NullValue {
                        path: path.to_path_buf(),
                        column: name.clone(),
                        row,
                    });
                }
                report
                    .skipped
                    .push((name.clone(), format!("a null at row {row}")));
                dropped.push(k);
                continue;
            }
            extend_from_arrow(column, array.as_ref());
        }
        row0 += batch.num_rows();
    }
    let mut k = 0;
    table.columns.retain(|_| {
        k += 1;
        !dropped.contains(&(k - 1))
    });
    Ok((table, report))
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
        DataType::Timestamp(..) => Column::I64(Vec::new()),
        _ => return None,
    })
}

/// The values of a primitive Arrow array, widened to `U` (float32 to f64, narrower integers to
/// 64 bits: exact).
fn widened<T: ArrowPrimitiveType, U: From<T::Native>>(
    array: &dyn Array,
) -> impl Iterator<Item = U> + '_ {
    array
        .as_primitive::<T>()
        .values()
        .iter()
        .map(|&x| U::from(x))
}

/// Appends a null-free Arrow array of a type accepted by [`empty_column_for`].
fn extend_from_arrow(column: &mut Column, array: &dyn Array) {
    match (column, array.data_type()) {
        (Column::F64(v), DataType::Float64) => {
            v.extend_from_slice(array.as_primitive::<Float64Type>().values())
        }
        (Column::F64(v), DataType::Float32) => v.extend(widened::<Float32Type, f64>(array)),
        (Column::I64(v), DataType::Int64) => {
            v.extend_from_slice(array.as_primitive::<Int64Type>().values())
        }
        (Column::I64(v), DataType::Int32) => v.extend(widened::<Int32Type, i64>(array)),
        (Column::I64(v), DataType::Int16) => v.extend(widened::<Int16Type, i64>(array)),
        (Column::I64(v), DataType::Int8) => v.extend(widened::<Int8Type, i64>(array)),
        (Column::U64(v), DataType::UInt64) => {
            v.extend_from_slice(array.as_primitive::<UInt64Type>().values())
        }
        (Column::U64(v), DataType::UInt32) => v.extend(widened::<UInt32Type, u64>(array)),
        (Column::U64(v), DataType::UInt16) => v.extend(widened::<UInt16Type, u64>(array)),
        (Column::U64(v), DataType::UInt8) => v.extend(widened::<UInt8Type, u64>(array)),
        (Column::I64(v), DataType::Timestamp(unit, _)) => {
            // Nanoseconds since the epoch, in integers (f64 seconds since 1970 would keep only
            // ~0.2 us); the time zone only changes how a timestamp is shown.
            let ns_per_tick = match unit {
                TimeUnit::Second => 1_000_000_000,
                TimeUnit::Millisecond => 1_000_000,
                TimeUnit::Microsecond => 1_000,
                TimeUnit::Nanosecond => 1,
            };
            let ticks = arrow::compute::cast(array, &DataType::Int64)
                .expect("a timestamp casts to its int64 ticks");
            v.extend(
                ticks
                    .as_primitive::<Int64Type>()
                    .values()
                    .iter()
                    .map(|&x| x.saturating_mul(ns_per_tick)),
            )
        }
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
