"""npe2 dock widget: runs ``maps`` on the selected layer's source sequence and, when a model is chosen,
``classify`` on those maps, in a worker thread with a progress bar; the results open as layers
(:mod:`.reader`). Needs napari and Qt (imported when the widget is made, never by the reader/writer)."""

from __future__ import annotations

from typing import Any


def MapsWidget(napari_viewer: Any) -> Any:  # noqa: N802 (npe2 names a widget contribution like a class)
    """The dock widget: resolutions, metrics, model, a Run button and a progress bar."""
    from qtpy.QtWidgets import QComboBox, QLabel, QLineEdit, QProgressBar, QPushButton, QVBoxLayout, QWidget

    from napari.qt.threading import thread_worker

    w = QWidget()
    lay = QVBoxLayout(w)
    res = QLineEdit("original")
    metrics = QLineEdit("liv,ocds,mean_db")
    model = QComboBox()
    model.addItem("(no classification)")
    try:
        from classifier import shipped_models

        for name in shipped_models():
            model.addItem(name)
    except ImportError:  # the classifier is optional here
        pass
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
    def work(path: str, resolutions: list[str], mets: list[str], model_name: str | None):
        from ..measured.io import read_sequence
        from ..measured.maps import compute_maps

        maps = compute_maps(read_sequence(path), resolutions, metrics=mets, progress=True)
        classes = None
        if model_name:
            from classifier import classify_maps, load_model

            classes = classify_maps(maps, load_model(model_name))
        return maps, classes

    def done(result: Any) -> None:
        maps, classes = result
        import tempfile
        from pathlib import Path

        from ..measured.mapsfile import write_maps
        from .reader import read_maps_layers

        with tempfile.TemporaryDirectory() as d:
            for data, attrs, kind in read_maps_layers(write_maps(Path(d) / "maps.npz", maps)):
                napari_viewer._add_layer_from_data(data, attrs, kind)
        if classes is not None:
            napari_viewer.add_labels(classes.labels.astype("int32") + 1, name="classes")
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
        name = model.currentText()
        worker = work(path, [r.strip() for r in res.text().split(";") if r.strip()],
                      [m.strip() for m in metrics.text().split(",") if m.strip()],
                      None if name.startswith("(") else name)
        worker.returned.connect(done)
        worker.errored.connect(lambda err: (bar.hide(), status.setText(f"error: {err}")))
        worker.start()

    run.clicked.connect(start)
    return w
