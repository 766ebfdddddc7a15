"""Reports: a self-contained ``report.html`` per plant and one per batch.

- :func:`plantsplat.report.plant.write_report`: frames with mask overlays, camera path, test-view renders, image
  metrics, traits with the measurement figure, run times, and an interactive 3D viewer of the Gaussian splat and
  the point cloud (Spark + three.js, vendored by ``scripts/vendor_viewer.sh``, inlined; opens from ``file://``).
- :func:`plantsplat.report.batch.write_batch_report`: traits of every plant, accuracy table, interactive scatter
  plots (plotly), links to each plant's report.

The options are :mod:`plantsplat.report.config`; the writers load OpenCV, matplotlib and plotly, so they are
imported where they are used.

Usage:
    from plantsplat.report.plant import write_report
    write_report("ws/plant_01")
"""

from plantsplat.report.config import ReportConfig

__all__ = ["ReportConfig"]
