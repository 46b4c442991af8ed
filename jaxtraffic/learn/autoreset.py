"""The gain environment's automatic reset where an episode ended, without a host round trip per step on a CPU
(``learn.env.auto_reset``): under ``vmap`` (any nesting) the environments of all batch levels are flattened into one
batch and a ``lax.cond`` on any-done builds fresh episodes only at the steps where some environment finished. The
reset itself is the environment's select of a fresh episode (``select``), applied through ``custom_vmap`` rules;
the delay buffer's storage stays out of the branches (a reset never touches it)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

Array = jax.Array
# select(done, key, state, obs, params, eq) -> (obs, state): a fresh episode where done (one environment)
Select = Callable[..., tuple[Array, Any]]


def reset_where_done(select: Select, done: Array, key: Array, state: Any, obs: Array, params: Any,
                     eq: tuple[Array, Array]) -> tuple[Array, Any]:
    """(obs, state) with a fresh episode (``select``'s, drawn from ``key``) where ``done``, built only when some
    environment of the batch finished; with batched ``params`` (a ``vmap`` over scenarios) ``select`` everywhere."""
    stripped, data = _split_buffer(state)
    p_leaves, p_def = jax.tree.flatten(params)
    # Python numbers stay Python numbers (static, part of the cache key): the reset's arithmetic on them
    # (e.g. delay_min / dt in double precision) must stay what it is in a plain call
    static = tuple((i, x) for i, x in enumerate(p_leaves) if isinstance(x, (int, float, bool)))
    p_def = (p_def, static)
    traced = tuple(x for x in p_leaves if not isinstance(x, (int, float, bool)))
    s_leaves, s_def = jax.tree.flatten(stripped)  # (custom_vmap unflattens its flags into the argument trees:
    # only plain containers may appear there, not dataclasses that check their fields, like TrafficParams)
    obs, new = _resetters(select, p_def, s_def)(done, key, tuple(s_leaves), obs, traced, eq)
    return obs, _with_buffer(jax.tree.unflatten(s_def, new), data)


def _split_buffer(state):
    """(state without the delay buffer's storage, the storage): a reset never touches the storage
    (``initial_state(..., sent=...)``), so it stays out of the branches."""
    sent = state.plant.sent
    return state.replace(plant=state.plant.replace(sent=sent.replace(data=None))), sent.data


def _with_buffer(state, data: Array):
    return state.replace(plant=state.plant.replace(sent=state.plant.sent.replace(data=data)))


def _params_of(p_def, p_leaves) -> Any:
    """The parameters from ``reset_where_done``'s (treedef, static numbers) and its array leaves."""
    treedef, static = p_def
    leaves, arrays, fixed = [], iter(p_leaves), dict(static)
    for i in range(treedef.num_leaves):
        leaves.append(fixed[i] if i in fixed else next(arrays))
    return jax.tree.unflatten(treedef, leaves)


def _flat_select(select: Select, p_def, s_def):
    """``select`` on flattened state and parameter leaves (returns (obs, state leaves))."""
    def sel(done, key, s_leaves, obs, p_leaves, eq):
        obs, new = select(done, key, jax.tree.unflatten(s_def, s_leaves), obs, _params_of(p_def, p_leaves), eq)
        return obs, tuple(jax.tree.leaves(new))
    return sel


def _cond_reset(done, key, s_leaves, obs, p_leaves, eq, select, p_def, s_def, batched: bool):
    sel = _flat_select(select, p_def, s_def)
    fn = jax.vmap(sel, (0, 0, 0, 0, None, None)) if batched else sel
    return jax.lax.cond(jnp.any(done), lambda: fn(done, key, s_leaves, obs, p_leaves, eq),
                        lambda: (obs, tuple(s_leaves)))


def _broadcast(tree, batched, size: int):
    return jax.tree.map(lambda x, b: x if b else jnp.broadcast_to(x, (size,) + jnp.shape(x)), tree, batched)


def _all_batched(out):
    return out, jax.tree.map(lambda _: True, out)


def _any_batched(tree) -> bool:
    return any(jax.tree.leaves(tree))


@functools.cache
def _resetters(select: Select, p_def, s_def):
    """The per-environment and the batched reset by ``select`` for the parameter tree ``p_def`` (custom_vmap
    rules)."""

    @custom_vmap
    def many(done, key, state, obs, p_leaves, eq):  # leading axis: the environments
        return _cond_reset(done, key, state, obs, p_leaves, eq, select, p_def, s_def, batched=True)

    @many.def_vmap
    def many_rule(size, in_batched, done, key, state, obs, p_leaves, eq):
        if _any_batched(in_batched[4:]):  # batched parameters: per environment, a select
            axes = tuple(jax.tree.map(lambda b: 0 if b else None, x) for x in in_batched[4:])
            sel = jax.vmap(jax.vmap(_flat_select(select, p_def, s_def), (0, 0, 0, 0, None, None)), (0, 0, 0, 0) + axes)
            args = _broadcast((done, key, state, obs), tuple(in_batched[:4]), size)
            return _all_batched(sel(*args, p_leaves, eq))
        args = _broadcast((done, key, state, obs), tuple(in_batched[:4]), size)
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), args)  # (size, B, ...) -> (size B, ...)
        out = many(*flat, p_leaves, eq)
        return _all_batched(jax.tree.map(lambda x: x.reshape((size, -1) + x.shape[1:]), out))

    @custom_vmap
    def one(done, key, state, obs, p_leaves, eq):
        return _cond_reset(done, key, state, obs, p_leaves, eq, select, p_def, s_def, batched=False)

    @one.def_vmap
    def one_rule(size, in_batched, done, key, state, obs, p_leaves, eq):
        args = _broadcast((done, key, state, obs), tuple(in_batched[:4]), size)
        if _any_batched(in_batched[4:]):
            axes = tuple(jax.tree.map(lambda b: 0 if b else None, x) for x in in_batched[4:])
            sel = jax.vmap(_flat_select(select, p_def, s_def), (0, 0, 0, 0) + axes)
            return _all_batched(sel(*args, p_leaves, eq))
        return _all_batched(many(*args, p_leaves, eq))

    return one
