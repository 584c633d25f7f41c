"""`capvector vector extract | merge | mean | stats | spectrum`: capability-vector arithmetic on safetensors
checkpoints."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from capvector.flows.cli.common import HomeOption, JsonOption, Table, console, err, print_json, workspace

DtypeOption = Annotated[
    str | None,
    typer.Option(
        "--dtype",
        help="compute in this dtype (float32 | float64); lets floats of different dtypes meet "
        "(a bf16 fine-tune against an fp32 base)",
    ),
]
OutDtypeOption = Annotated[
    str | None,
    typer.Option(
        "--out-dtype", help="float dtype to write (float32 | bfloat16 | ...; default: the reference's)"
    ),
]
StripOption = Annotated[
    str | None,
    typer.Option("--strip-prefix", help="take this prefix off the other inputs' tensor names (model.)"),
]
AddOption = Annotated[
    str | None, typer.Option("--add-prefix", help="put this prefix before the other inputs' tensor names")
]
ShardOption = Annotated[
    str | None,
    typer.Option(
        "--out-shard-size",
        help="a folder output's largest shard (5GB, 500MiB; HF's index layout); default 2 GiB",
    ),
]


def _real(dtype, out_dtype, strip_prefix, add_prefix, out_shard_size):
    from capvector.tasks.vector_commands import RealCheckpoints

    return RealCheckpoints(dtype, out_dtype, strip_prefix, add_prefix, out_shard_size)


vector_app = typer.Typer(
    no_args_is_help=True, help="Capability-vector arithmetic on safetensors checkpoints."
)


@vector_app.command("extract")
def vector_extract(
    minuend: Annotated[str, typer.Argument(help="θ_ao: file, sharded dir or artifact id")],
    subtrahend: Annotated[str, typer.Argument(help="θ_ft: file, sharded dir or artifact id")],
    out: Annotated[Path, typer.Option("-o", "--out", help="*.safetensors = one file, else a sharded dir")],
    base: Annotated[str | None, typer.Option(help="θ_pt the vector is meant for")] = None,
    include: Annotated[list[str] | None, typer.Option(help="tensor-name globs to include")] = None,
    exclude: Annotated[list[str] | None, typer.Option(help="tensor-name globs to exclude")] = None,
    dtype: DtypeOption = None,
    out_dtype: OutDtypeOption = None,
    strip_prefix: StripOption = None,
    add_prefix: AddOption = None,
    out_shard_size: ShardOption = None,
    home: HomeOption = None,
) -> None:
    """γ = MINUEND − SUBTRAHEND, streamed tensor by tensor; registered in the catalogue.

    A folder output gets the minuend folder's other files (config.json, ...) and a README.md card;
    --strip-prefix / --add-prefix map SUBTRAHEND's names onto MINUEND's."""
    from capvector.tasks.vector_commands import extract_cli

    real = _real(dtype, out_dtype, strip_prefix, add_prefix, out_shard_size)
    record = extract_cli(workspace(home), minuend, subtrahend, out, base, include, exclude, real)
    console.print(f"{out}  (artifact {record.id})")


@vector_app.command("merge")
def vector_merge(
    base: Annotated[str, typer.Argument(help="θ_pt: file, sharded dir or artifact id")],
    vectors: Annotated[list[str], typer.Option("--vector", help="a vector (repeatable)")],
    alphas: Annotated[list[float], typer.Option("--alpha", help="its coefficient (one per --vector)")],
    out: Annotated[Path, typer.Option("-o", "--out", help="*.safetensors = one file, else a sharded dir")],
    include: Annotated[list[str] | None, typer.Option(help="tensor-name globs to merge into")] = None,
    exclude: Annotated[list[str] | None, typer.Option(help="tensor-name globs to keep from base")] = None,
    force: Annotated[bool, typer.Option(help="merge even if a vector names another base")] = False,
    dtype: DtypeOption = None,
    out_dtype: OutDtypeOption = None,
    strip_prefix: StripOption = None,
    add_prefix: AddOption = None,
    out_shard_size: ShardOption = None,
    home: HomeOption = None,
) -> None:
    """BASE + Σ α_i·vector_i, streamed; registered in the catalogue with an edge per vector.

    A folder output gets BASE folder's other files (config.json, train_config.json, processors, ...)
    and a README.md card, so it loads where BASE loads; --strip-prefix / --add-prefix map the vectors'
    names onto BASE's."""
    from capvector.tasks.vector_commands import merge_cli

    if len(vectors) != len(alphas):
        raise typer.BadParameter(f"{len(vectors)} --vector but {len(alphas)} --alpha: give one α per vector")
    real = _real(dtype, out_dtype, strip_prefix, add_prefix, out_shard_size)
    record = merge_cli(
        workspace(home), base, list(zip(vectors, alphas, strict=True)), out, include, exclude, force, real
    )
    console.print(f"{out}  (artifact {record.id})")


@vector_app.command("mean")
def vector_mean(
    vectors: Annotated[list[str], typer.Argument(help="K ≥ 2 vectors: files, sharded dirs or artifact ids")],
    out: Annotated[Path, typer.Option("-o", "--out", help="*.safetensors = one file, else a sharded dir")],
    method: Annotated[str, typer.Option(help="mean | ties (TIES merging: trim, elect signs, mean)")] = "mean",
    density: Annotated[float, typer.Option(help="ties: the share of each tensor a vector keeps")] = 0.2,
    home: HomeOption = None,
) -> None:
    """γ̄ = mean of VECTORS (K seed draws: seed noise averaged out), streamed; an edge per input."""
    from capvector.tasks.vector_commands import mean_cli

    record = mean_cli(workspace(home), vectors, out, method, density)
    console.print(f"{out}  (artifact {record.id})")


@vector_app.command("stats")
def vector_stats(
    vector: Annotated[str, typer.Argument(help="vector: file, sharded dir or artifact id")],
    base: Annotated[str | None, typer.Option(help="θ_pt, for norms relative to the weights")] = None,
    reference: Annotated[str | None, typer.Option(help="a reference vector, e.g. θ_ft − θ_pt")] = None,
    level: Annotated[str, typer.Option(help="tensor | group | all")] = "group",
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Norms, relative norms, cosine and sign agreement per tensor / module group."""
    from capvector.tasks.vector_commands import stats_cli

    rows, record, reused = stats_cli(workspace(home), vector, base, reference)
    if as_json:
        print_json([r.model_dump() for r in rows])
        return
    table = Table("name", "numel", "‖γ‖", "‖γ‖/‖θ‖", "cos(ref)", "sign agree")
    for r in rows:
        if r.level != level:
            continue
        table.add_row(
            r.name,
            f"{r.numel:,}",
            f"{r.l2:.4g}",
            _fmt(r.relative_norm),
            _fmt(r.cosine),
            _fmt(r.sign_agreement),
        )
    console.print(table)
    said = "recorded before: reused" if reused else "recorded"
    err.print(f"stats artifact {record.id} ({said})", highlight=False)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.4g}"


@vector_app.command("spectrum")
def vector_spectrum(
    a: Annotated[str, typer.Argument(help="A of B − A, or a vector: file, sharded dir or artifact id")],
    b: Annotated[str | None, typer.Argument(help="B, the checkpoint after the update")] = None,
    figure: Annotated[
        Path | None, typer.Option("--figure", help="PNG: rank at 90 / 99 % energy per tensor over full rank")
    ] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Singular values of each 2-D tensor of B − A (or of a vector): the ranks holding 50 / 90 / 99 % of
    its energy, by module kind (attention, mlp, encoder, action_head, other); registered in the catalogue."""
    from capvector.tasks.vector_commands import spectrum_cli

    rows, record, reused = spectrum_cli(workspace(home), a, b)
    if figure is not None:
        _plot_spectrum(rows, figure)
    if as_json:
        print_json([r.model_dump() for r in rows])
    else:
        console.print(_spectrum_table(rows))
    said = "recorded before: reused" if reused else "recorded"
    err.print(f"spectrum artifact {record.id} ({said})", highlight=False)


def _by_kind(rows: list) -> list:
    """The rows grouped by module kind (in `KIND_ORDER`), each kind's in checkpoint order."""
    from capvector.core.vectors.spectrum import KIND_ORDER

    return sorted(rows, key=lambda r: KIND_ORDER.index(r.kind))


def _spectrum_table(rows: list) -> object:
    table = Table("kind", "tensor", "shape", "full rank", "rank 50%", "rank 90%", "rank 99%", "σ₁")
    for r in _by_kind(rows):
        ranks = (str(n) for n in (r.full_rank, r.rank50, r.rank90, r.rank99))
        table.add_row(r.kind, r.tensor, f"{r.rows}×{r.cols}", *ranks, f"{r.top:.4g}")
    return table


def _plot_spectrum(rows: list, path: Path) -> None:
    """Per 2-D tensor (checkpoint order), its rank at 90 % and at 99 % energy as a share of its full
    rank, one marker per module kind: where an update is low-rank, and in which modules."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from capvector.core.vectors.spectrum import KIND_ORDER

    fig, axes = plt.subplots(2, 1, sharex=True, figsize=(max(6.0, 0.1 * len(rows) + 2), 5))
    for ax, (field, energy) in zip(axes, (("rank90", "90 %"), ("rank99", "99 %")), strict=True):
        for kind, marker in zip(KIND_ORDER, "os^Dx", strict=True):
            at = [i for i, r in enumerate(rows) if r.kind == kind]
            if at:
                share = [getattr(rows[i], field) / rows[i].full_rank for i in at]
                ax.scatter(at, share, marker=marker, label=kind, s=18)
        ax.set_ylabel(f"rank at {energy} energy\n/ full rank")
        ax.set_ylim(0, 1.08)
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))  # beside: no point hidden
    axes[1].set_xlabel("2-D tensor, in checkpoint order")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
