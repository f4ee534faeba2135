"""The capture report: one self-contained HTML page (images inlined as PNG data URIs). See objcam/stages/report.py."""
