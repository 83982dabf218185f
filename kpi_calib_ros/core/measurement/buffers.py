"""Fast numeric evaluation of mapped CasADi functions straight into numpy buffers."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

import casadi as ca
import numpy as np

__all__ = ['Mapped', 'call_mapped']


@dataclass(frozen=True)
class Mapped:
    """A mapped function, its inputs' shapes and where each output's nonzeros go.

    Read from its sparsity once: reading an output's triplet on every call cost an eighth
    of the evaluation of a fit's Jacobian.
    """

    fn: ca.Function
    # (rows, columns) of every input, all dense.
    inputs: tuple[tuple[int, int], ...]
    # (rows, columns, nonzero rows and columns; None: dense) of every output.
    outputs: tuple[tuple[int, int, tuple[np.ndarray, np.ndarray] | None], ...]

    @classmethod
    def of(cls, fn: ca.Function) -> Mapped:
        """Return ``fn`` with its layout; only dense inputs are read."""
        for i in range(fn.n_in()):
            if not fn.sparsity_in(i).is_dense():
                raise ValueError(f'input {i} of {fn.name()} is sparse; only dense inputs are '
                                 'read')
        outputs = []
        for j in range(fn.n_out()):
            sparsity = fn.sparsity_out(j)
            placed = None
            if not sparsity.is_dense():
                r, c = sparsity.get_triplet()
                placed = (np.asarray(r, dtype=np.intp), np.asarray(c, dtype=np.intp))
            outputs.append((sparsity.size1(), sparsity.size2(), placed))
        return cls(fn, tuple((fn.size1_in(i), fn.size2_in(i)) for i in range(fn.n_in())),
                   tuple(outputs))


def call_mapped(mapped: Mapped, args: list[np.ndarray]) -> list[np.ndarray]:
    """Evaluate the mapped function at numeric ``args`` into dense ndarrays, by its buffers.

    Calling a Function with arrays returns CasADi matrices, and reading a mapped Jacobian
    (mostly structural zeros, each row's block) back into numpy element by element took
    ten times as long as the evaluation. Here the inputs are handed over as column-major
    buffers (a column broadcast over the mapped rows) and each output's nonzeros written
    straight into an array, then placed at its sparsity. The values are the same bits.
    A buffer is made per call, so calls from several threads do not share one.
    """
    # CasADi's stubs name a size argument its Python binding does not take.
    buffer, evaluate = cast(Any, mapped.fn).buffer()
    keep = []
    for i, (value, shape) in enumerate(zip(args, mapped.inputs)):
        array = np.asarray(value, float)
        column = array[:, None] if array.ndim == 1 else array
        column_major = np.broadcast_to(column, shape).ravel(order='F')
        keep.append(column_major)
        buffer.set_arg(i, column_major.data)
    nonzeros = [np.zeros(rows * cols if placed is None else len(placed[0]))
                for rows, cols, placed in mapped.outputs]
    for j, out in enumerate(nonzeros):
        buffer.set_res(j, out.data)
    evaluate()
    dense = []
    for out, (rows, cols, placed) in zip(nonzeros, mapped.outputs):
        if placed is None:
            dense.append(out.reshape(cols, rows).T)
            continue
        full = np.zeros((rows, cols))
        full[placed] = out
        dense.append(full)
    return dense
