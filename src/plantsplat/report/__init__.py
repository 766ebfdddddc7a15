"""Reports: a self-contained ``report.html`` per plant and one per batch.

- :func:`write_report`: frames with mask overlays, camera path, test-view renders, image metrics, traits
  with the measurement figure, run times, and an interactive 3D viewer of the Gaussian splat and the
  point cloud (Spark + three.js, vendored by ``scripts/vendor_viewer.sh``, inlined; opens from ``file://``).
- :func:`write_batch_report`: traits of every plant, accuracy table, interactive scatter plots (plotly),
  links to each plant's report.

Usage:
    from plantsplat.report import write_report
    write_report("ws/plant_01")
"""

from plantsplat.report.batch import write_batch_report
from plantsplat.report.config import ReportConfig
from plantsplat.report.plant import build_report_html, write_report

__all__ = ["ReportConfig", "build_report_html", "write_batch_report", "write_report"]
