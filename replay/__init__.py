"""The application layer: recordings → sample streams → :class:`pdr_mag.pipeline.HeadingPipeline` → sinks."""
