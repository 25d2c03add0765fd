# %% [markdown]
# # Error tables of a calibration, plotted
#
# A notebook-style script (cells marked `# %%`, as VS Code, Spyder and Jupytext read
# them; it runs as a plain script too):
#
#     python examples/plot_error_tables.py [errors.csv] [figure.png]
#
# It reads an error-table CSV written by `xmalign post` (default: the example
# `examples/errors.csv`) through the Python API (docs/api.md) and draws, per
# axis, the translation errors (µm) and the rotation errors (µrad) with their
# U95 band; extrapolated points are drawn hollow.

# %%
import sys
from pathlib import Path

import matplotlib

if "ipykernel" not in sys.modules:  # a script: draw into a file, no window
    matplotlib.use("Agg")
import matplotlib.pyplot as plt

from xmalign import api

HERE = Path(__file__).resolve().parent
errors_path = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "errors.csv"
figure_path = Path(sys.argv[2]) if len(sys.argv) > 2 else Path("error-tables.png")

# %% [markdown]
# One DataFrame per axis, indexed by the position along it; the unit is in
# every column name (`EXX_um`, `EXX_u95_um`, `EBX_urad`).

# %%
tables = api.read_error_tables(errors_path)
frames = api.error_table_frames(tables)
frames["X"].filter(like="_um").head()

# %%
figure, axes = plt.subplots(2, len(frames), figsize=(4 * len(frames), 6), squeeze=False)
for column, (axis, frame) in enumerate(frames.items()):
    for row, unit in enumerate(("um", "urad")):
        ax = axes[row, column]
        names = [c.removesuffix(f"_{unit}") for c in frame.columns if c.endswith(f"_{unit}")]
        for name in (n for n in names if not n.endswith("_u95")):
            values = frame[f"{name}_{unit}"].dropna()
            u95 = frame[f"{name}_u95_{unit}"].reindex(values.index).fillna(0.0)
            measured = frame[f"{name}_measured"].reindex(values.index).fillna(True).astype(bool)
            (line,) = ax.plot(values.index, values, label=name)
            ax.fill_between(values.index, values - u95, values + u95, alpha=0.15)
            ax.plot(
                values.index[~measured],
                values[~measured],
                "o",
                mfc="none",
                color=line.get_color(),
            )
        ax.set_title(f"{axis}: {'translations' if unit == 'um' else 'rotations'}")
        ax.set_xlabel(f"{axis} position / mm")
        ax.set_ylabel("µm" if unit == "um" else "µrad")
        ax.legend(fontsize=6, ncol=2)
        ax.grid(True, alpha=0.3)
figure.suptitle(f"Error tables, U95 bands: {errors_path.name}")
figure.tight_layout()

# %%
figure.savefig(figure_path, dpi=100)
print(f"wrote {figure_path}")
