"""npe2 dock widget: runs ``maps`` on the selected layer's source sequence and, when asked, ``doct-classify``
on those maps (the command, in a subprocess: torchdoct never imports the classifier), in a worker thread
with a progress bar; the results open as layers (:mod:`.reader`). Needs napari and Qt (imported when the
widget is made, never by the reader/writer)."""

from __future__ import annotations

from typing import Any


def MapsWidget(napari_viewer: Any) -> Any:
    """The dock widget: resolutions, metrics, model, a Run button and a progress bar."""
    from napari.qt.threading import thread_worker
    from qtpy.QtWidgets import QComboBox, QLabel, QLineEdit, QProgressBar, QPushButton, QVBoxLayout, QWidget

    w = QWidget()
    lay = QVBoxLayout(w)
    res = QLineEdit("original")
    metrics = QLineEdit("liv,ocds,mean_db")
    model = QComboBox()
    model.addItems(["(no classification)", "(shipped default model)"])
    run, bar, status = QPushButton("Run maps"), QProgressBar(), QLabel("")
    bar.setRange(0, 0)
    bar.hide()
    for label, widget in (("resolutions (; separated)", res), ("metrics", metrics), ("classify with", model)):
        lay.addWidget(QLabel(label))
        lay.addWidget(widget)
    lay.addWidget(run)
    lay.addWidget(bar)
    lay.addWidget(status)

    def source() -> str:
        layer = napari_viewer.layers.selection.active
        src = getattr(layer, "source", None)
        path = getattr(src, "path", None)
        if not path:
            raise ValueError("select a layer opened from a sequence file")
        return str(path)

    @thread_worker
    def work(path: str, resolutions: list[str], mets: list[str], classify: bool):
        import shutil
        import subprocess
        import tempfile
        from pathlib import Path

        from ..measured.io import read_sequence
        from ..measured.maps import compute_maps
        from ..measured.mapsfile import write_maps
        from .reader import read

        maps = compute_maps(read_sequence(path), resolutions, metrics=mets, signature=classify, progress=True)
        with tempfile.TemporaryDirectory() as d:
            mpath = write_maps(Path(d) / "maps.npz", maps)
            layers = read(mpath)
            if classify:
                exe = shutil.which("doct-classify")
                if exe is None:
                    raise ValueError("doct-classify is not installed (pip install the classifier with torchdoct)")
                subprocess.run(
                    [exe, str(mpath), "--out", str(Path(d) / "classes")], check=True, capture_output=True, text=True
                )
                layers += read(Path(d) / "classes" / "classes.tif")
        return layers

    def done(layers: Any) -> None:
        for data, attrs, kind in layers:
            getattr(napari_viewer, f"add_{kind}")(data, **attrs)
        bar.hide()
        status.setText("done")

    def start() -> None:
        try:
            path = source()
        except ValueError as err:
            status.setText(str(err))
            return
        bar.show()
        status.setText("computing maps …")
        worker = work(
            path,
            [r.strip() for r in res.text().split(";") if r.strip()],
            [m.strip() for m in metrics.text().split(",") if m.strip()],
            model.currentIndex() == 1,
        )
        worker.returned.connect(done)
        worker.errored.connect(lambda err: (bar.hide(), status.setText(f"error: {err}")))
        worker.start()

    run.clicked.connect(start)
    return w
