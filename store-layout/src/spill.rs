//! Image columns written to a temporary file as their pages are encoded, instead of to memory.
//!
//! A steps file's row group is encoded column by column in memory (`ArrowColumnWriter`) and
//! spliced into the file when it closes, between episodes; one ALOHA episode is 0.5-2 GB of raw
//! frames, several hundred MB as PNG, so its image columns cannot wait in memory. Each image
//! leaf of the open row group gets a [`SpillColumn`]: a Parquet column writer whose pages go to
//! an unnamed temporary file (gone when dropped), copied into the steps file when the row group
//! closes (`SerializedRowGroupWriter::append_column`). Memory is one page per camera.

use std::fs::File;
use std::io::Write;

use parquet::column::page::{CompressedPage, PageWriteSpec, PageWriter};
use parquet::column::writer::{get_column_writer, ColumnCloseResult, ColumnWriter};
use parquet::data_type::ByteArray;
use parquet::errors::ParquetError;
use parquet::file::properties::WriterPropertiesPtr;
use parquet::file::writer::{SerializedPageWriter, SerializedRowGroupWriter, TrackedWrite};
use parquet::schema::types::ColumnDescPtr;

use crate::StoreError;

/// Pages serialized to a temporary file exactly as the steps file's own page writer would.
struct FilePages {
    sink: TrackedWrite<File>,
}

impl PageWriter for FilePages {
    fn write_page(&mut self, page: CompressedPage) -> parquet::errors::Result<PageWriteSpec> {
        SerializedPageWriter::new(&mut self.sink).write_page(page)
    }
    fn close(&mut self) -> parquet::errors::Result<()> {
        self.sink.flush().map_err(|e| ParquetError::External(Box::new(e)))
    }
}

/// One binary (image) leaf of the open row group, its pages in a temporary file.
pub(crate) struct SpillColumn {
    writer: ColumnWriter<'static>,
    /// The same file as the page writer's (read back when the row group closes).
    file: File,
}

/// A spilled column chunk, closed, waiting to be copied into the steps file.
pub(crate) struct SpilledChunk {
    file: File,
    close: ColumnCloseResult,
}

impl SpillColumn {
    pub(crate) fn new(descr: ColumnDescPtr, props: WriterPropertiesPtr) -> Result<Self, StoreError> {
        let file = tempfile::tempfile().map_err(|e| {
            StoreError::invalid(format!("cannot create a temporary file for image pages: {e}"))
        })?;
        let reader = file.try_clone().map_err(|e| {
            StoreError::invalid(format!("cannot reopen a temporary file for image pages: {e}"))
        })?;
        let pages = FilePages { sink: TrackedWrite::new(file) };
        let writer = get_column_writer(descr, props, Box::new(pages));
        if !matches!(writer, ColumnWriter::ByteArrayColumnWriter(_)) {
            return Err(StoreError::invalid("an image column must be a binary column"));
        }
        Ok(SpillColumn { writer, file: reader })
    }

    /// Writes `frames` as one page (the writer properties close a page after each call).
    pub(crate) fn write_page(&mut self, frames: Vec<Vec<u8>>) -> Result<(), StoreError> {
        let values: Vec<ByteArray> = frames.into_iter().map(ByteArray::from).collect();
        match &mut self.writer {
            ColumnWriter::ByteArrayColumnWriter(w) => {
                w.write_batch(&values, None, None)?;
                Ok(())
            }
            _ => Err(StoreError::invalid("an image column must be a binary column")),
        }
    }

    /// Encoded bytes so far.
    pub(crate) fn bytes_written(&self) -> usize {
        match &self.writer {
            ColumnWriter::ByteArrayColumnWriter(w) => w.get_total_bytes_written() as usize,
            _ => 0,
        }
    }

    pub(crate) fn close(self) -> Result<SpilledChunk, StoreError> {
        let close = self.writer.close()?;
        Ok(SpilledChunk { file: self.file, close })
    }
}

impl SpilledChunk {
    pub(crate) fn bytes(&self) -> usize {
        self.close.metadata.compressed_size().max(0) as usize
    }

    /// Copies the chunk into the row group being written (as its next column).
    pub(crate) fn append_to_row_group<W: Write + Send>(
        self,
        rg: &mut SerializedRowGroupWriter<'_, W>,
    ) -> Result<(), StoreError> {
        rg.append_column(&self.file, self.close)?;
        Ok(())
    }
}
