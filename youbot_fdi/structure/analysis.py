"""Structural analysis: matching, overdetermined part, MSO sets, fault signatures, isolability.

Algorithms (Blanke et al., "Diagnosis and Fault-Tolerant Control", ch. 5; Krysander, Åslund and
Nyberg 2008 for the MSO sets):

- a maximum matching between equations and unknowns (scipy's Hopcroft-Karp);
- the structurally overdetermined part M+ of a set of equations: the equations reachable from an
  unmatched equation by alternating paths (Dulmage-Mendelsohn);
- the minimal structurally overdetermined (MSO) sets: every PSO set of redundancy 1 reached by
  removing one equation at a time and taking M+ (Krysander's basic algorithm, memoised);
- single-fault detectability and isolability from the fault signature of the MSO sets: f_i is
  isolable from f_j if some MSO is sensitive to f_i and not to f_j.

Labels follow the report's Table 4.4: ``n`` not detectable, ``d`` detectable only, ``i`` isolable
from every other fault.
"""
from dataclasses import dataclass
from itertools import combinations

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import maximum_bipartite_matching

from youbot_fdi.errors import ModelError

UNMATCHED = -1


def maximum_matching(incidence):
    """For each equation (row) the index of its matched unknown (column), or -1.

    Parameters
    ----------
    incidence : ndarray of bool, shape (n_equations, n_unknowns)
    """
    incidence = np.asarray(incidence, dtype=bool)
    if incidence.size == 0:
        return np.full(incidence.shape[0], UNMATCHED, dtype=int)
    graph = scipy.sparse.csr_matrix(incidence.astype(np.int8))
    return np.asarray(maximum_bipartite_matching(graph, perm_type='column'), dtype=int)


def overdetermined_part(incidence, rows):
    """M+ of the equations ``rows``: a sorted tuple of row indices.

    Unknowns not appearing in ``rows`` are ignored.
    """
    rows = sorted(rows)
    if not rows:
        return ()
    sub = incidence[rows]
    columns = np.flatnonzero(sub.any(axis=0))
    sub = sub[:, columns]
    match = maximum_matching(sub)
    eq_of_var = np.full(len(columns), UNMATCHED, dtype=int)
    for eq, var in enumerate(match):
        if var != UNMATCHED:
            eq_of_var[var] = eq
    reached = [eq for eq in range(len(rows)) if match[eq] == UNMATCHED]
    seen = set(reached)
    while reached:
        eq = reached.pop()
        for var in np.flatnonzero(sub[eq]):
            partner = eq_of_var[var]
            if partner != UNMATCHED and partner not in seen:
                seen.add(partner)
                reached.append(partner)
    return tuple(sorted(rows[eq] for eq in seen))


def redundancy(incidence, rows):
    """Structural redundancy of a PSO set: equations minus the unknowns they contain."""
    rows = list(rows)
    if not rows:
        return 0
    return len(rows) - int(incidence[rows].any(axis=0).sum())


def find_msos(incidence):
    """All MSO sets of the model, each a sorted tuple of equation indices, sorted."""
    found = set()
    visited = set()

    def search(pso):
        if pso in visited:
            return
        visited.add(pso)
        if redundancy(incidence, pso) == 1:
            found.add(pso)
            return
        for eq in pso:
            reduced = overdetermined_part(incidence, [e for e in pso if e != eq])
            if reduced:
                search(reduced)

    top = overdetermined_part(incidence, range(incidence.shape[0]))
    if top:
        search(top)
    return sorted(found, key=lambda s: (len(s), s))


def parity_relations(incidence, matching):
    """Residual equation sets obtained by backtracking a matching (the report's parity relations).

    Parameters
    ----------
    incidence : ndarray of bool, shape (n_equations, n_unknowns)
    matching : ndarray of int, shape (n_equations,)
        Matched unknown per equation, -1 for unmatched.

    Returns
    -------
    dict
        Unmatched equation index -> sorted tuple of the equations its residual uses, for every
        unmatched equation whose unknowns can all be computed.
    """
    eq_of_var = {int(var): eq for eq, var in enumerate(matching) if var != UNMATCHED}
    relations = {}
    for start in np.flatnonzero(np.asarray(matching) == UNMATCHED):
        used, stack, computable = {int(start)}, [int(start)], True
        while stack and computable:
            eq = stack.pop()
            for var in np.flatnonzero(incidence[eq]):
                if int(var) == matching[eq]:
                    continue
                source = eq_of_var.get(int(var))
                if source is None:
                    computable = False
                    break
                if source not in used:
                    used.add(source)
                    stack.append(source)
        if computable:
            relations[int(start)] = tuple(sorted(used))
    return relations


def isolability_from_signatures(signatures):
    """Single-fault isolability from a fault signature matrix.

    Parameters
    ----------
    signatures : ndarray of bool, shape (n_tests, n_faults)
        ``signatures[t, f]``: test t is sensitive to fault f.

    Returns
    -------
    detectable : ndarray of bool, shape (n_faults,)
    not_isolable : ndarray of bool, shape (n_faults, n_faults)
        ``[i, j]`` is True when fault i cannot be isolated from fault j (always on the diagonal;
        a whole row for an undetectable fault), the toolbox's isolability-matrix convention.
    """
    signatures = np.asarray(signatures, dtype=bool)
    detectable = signatures.any(axis=0)
    # i is isolable from j if some test sees i and not j.
    isolable = (signatures[:, :, None] & ~signatures[:, None, :]).any(axis=0)
    not_isolable = ~isolable
    np.fill_diagonal(not_isolable, True)
    return detectable, not_isolable


def labels_from_isolability(detectable, not_isolable):
    """Per fault: ``n`` (not detectable), ``d`` (detectable only) or ``i`` (isolable from all)."""
    labels = []
    for i, seen in enumerate(detectable):
        if not seen:
            labels.append('n')
        elif not_isolable[i].sum() == 1:
            labels.append('i')
        else:
            labels.append('d')
    return labels


def isolation_classes(not_isolable, detectable):
    """Groups of detectable faults that no test tells apart (mutually non-isolable), as index lists."""
    n = len(detectable)
    classes, assigned = [], set()
    for i in range(n):
        if i in assigned or not detectable[i]:
            continue
        group = [j for j in range(n) if detectable[j] and not_isolable[i, j] and not_isolable[j, i]]
        assigned.update(group)
        classes.append(group)
    return classes


def select_tests(signatures):
    """A small subset of tests (row indices) with the same isolability as all of them.

    Forward greedy: repeatedly add the test that separates the most fault pairs not yet
    separated (and detects the most faults not yet detected); ties go to the test sensitive to
    the fewest faults, then to the lower index. Sparse signatures isolate more robustly.
    """
    signatures = np.asarray(signatures, dtype=bool)
    target_detectable, target_not_isolable = isolability_from_signatures(signatures)
    n_faults = signatures.shape[1]
    chosen = []
    detectable = np.zeros(n_faults, dtype=bool)
    not_isolable = np.ones((n_faults, n_faults), dtype=bool)
    while not (np.array_equal(detectable, target_detectable)
               and np.array_equal(not_isolable, target_not_isolable)):
        best, best_key = None, None
        for test in range(signatures.shape[0]):
            if test in chosen:
                continue
            row = signatures[test]
            separated = not_isolable & row[:, None] & ~row[None, :]
            gain = int(separated.sum()) + int((row & ~detectable).sum())
            key = (-gain, int(row.sum()), test)
            if gain > 0 and (best_key is None or key < best_key):
                best, best_key = test, key
        if best is None:
            break
        chosen.append(best)
        row = signatures[best]
        detectable |= row
        not_isolable &= ~(row[:, None] & ~row[None, :])
    return sorted(chosen)


def isolability_by_overdetermined_part(incidence, fault_rows):
    """Detectability and single-fault isolability without enumerating MSO sets.

    Fault i is detectable if its equation lies in M+ of the model, and isolable from fault j if
    it lies in M+ of the model without j's equation (M+ is the union of the MSO sets inside a set,
    so this equals the MSO-based definition). Same conventions as
    :func:`isolability_from_signatures`.
    """
    all_rows = range(incidence.shape[0])
    top = set(overdetermined_part(incidence, all_rows))
    detectable = np.array([row in top for row in fault_rows], dtype=bool)
    n = len(fault_rows)
    not_isolable = np.ones((n, n), dtype=bool)
    for j, removed in enumerate(fault_rows):
        reduced = set(overdetermined_part(incidence, [r for r in all_rows if r != removed]))
        for i, row in enumerate(fault_rows):
            if i != j and row in reduced:
                not_isolable[i, j] = False
    return detectable, not_isolable


@dataclass(frozen=True)
class ResidualSet:
    """The residuals the runtime uses: each an MSO set, with its fault signature."""

    names: list  # residual names
    equations: list  # per residual, a sorted tuple of equation indices
    signatures: np.ndarray  # (n_residuals, n_faults) bool
    declared: bool  # True: the model's own templates; False: selected by select_tests
    complete: bool  # True: they reach the model's full detectability and isolability


@dataclass(frozen=True)
class StructuralAnalysis:
    """Everything the analysis found about a model; index arrays follow the model's orders."""

    model: object
    matching: np.ndarray  # (n_equations,) matched unknown index or -1
    overdetermined: tuple  # equation indices of M+
    msos: list  # list of tuples of equation indices
    signatures: np.ndarray  # (n_msos, n_faults) bool
    detectable: np.ndarray  # (n_faults,) bool
    not_isolable: np.ndarray  # (n_faults, n_faults) bool
    labels: list  # per fault: 'n', 'd' or 'i'
    classes: list  # lists of fault indices
    residuals: 'ResidualSet'  # what the runtime evaluates
    parity: dict  # unmatched equation index -> tuple of equation indices

    @property
    def redundancy(self):
        """Structural redundancy of the model (of its M+)."""
        incidence = self.model.incidence(self.model.unknown)
        return redundancy(incidence, self.overdetermined)

    def equation_names(self, indices):
        """Names of equations given by index."""
        names = self.model.equation_names
        return [names[i] for i in indices]

    def label_map(self):
        """Fault name -> label."""
        return dict(zip(self.model.fault_names, self.labels))


def analyze(model):
    """Run the full structural analysis of a :class:`~youbot_fdi.structure.model.StructuralModel`."""
    incidence = model.incidence(model.unknown)
    matching = maximum_matching(incidence)
    msos = find_msos(incidence)
    fault_rows = model.fault_equation_index()
    signatures = np.array([[row in mso for row in fault_rows] for mso in msos], dtype=bool)
    signatures = signatures.reshape(len(msos), len(fault_rows))
    detectable, not_isolable = isolability_by_overdetermined_part(incidence, fault_rows)
    return StructuralAnalysis(
        model=model, matching=matching,
        overdetermined=overdetermined_part(incidence, range(len(model.equations))),
        msos=msos, signatures=signatures, detectable=detectable, not_isolable=not_isolable,
        labels=labels_from_isolability(detectable, not_isolable),
        classes=isolation_classes(not_isolable, detectable),
        residuals=runtime_residuals(model, msos, signatures, detectable, not_isolable),
        parity=parity_relations(incidence, matching))


def runtime_residuals(model, msos, signatures, detectable, not_isolable):
    """The model's declared residual templates (``reference['residuals']``), or a selection.

    Declared templates must each be an MSO set of the model; whether together they reach the
    model's full isolability is reported in ``complete``.
    """
    templates = model.reference.get('residuals') or {}
    if templates:
        index = {name: i for i, name in enumerate(model.equation_names)}
        position = {mso: k for k, mso in enumerate(msos)}
        names, sets, rows = [], [], []
        for name, equations in templates.items():
            unknown = [e for e in equations if e not in index]
            if unknown:
                msg = f'residual {name!r} of model {model.name!r} uses unknown equations {unknown}'
                raise ModelError(msg)
            rows_of = tuple(sorted(index[e] for e in equations))
            if rows_of not in position:
                msg = f'residual {name!r} of model {model.name!r} is not an MSO set'
                raise ModelError(msg)
            names.append(name)
            sets.append(rows_of)
            rows.append(position[rows_of])
        declared = True
    else:
        rows = select_tests(signatures) if len(msos) else []
        names = [f'r{k + 1}' for k in range(len(rows))]
        sets = [msos[k] for k in rows]
        declared = False
    chosen = signatures[rows] if rows else np.zeros((0, len(detectable)), dtype=bool)
    got_detectable, got_not_isolable = isolability_from_signatures(chosen)
    complete = (np.array_equal(got_detectable, detectable)
                and np.array_equal(got_not_isolable, not_isolable))
    return ResidualSet(names, sets, chosen, declared, complete)


def sensor_placement(model, candidates):
    """Which groups of extra sensors make the model's faults isolable.

    Parameters
    ----------
    model : StructuralModel
    candidates : dict
        Group name -> list of (sensor name, measured unknown variable).

    Returns
    -------
    list of dict
        One entry per combination of groups (empty one first): ``groups`` (tuple of names),
        ``non_isolable_pairs`` (ordered pairs of the *original* faults still not isolable) and
        ``labels`` (original fault -> label).
    """
    original = model.fault_names
    results = []
    names = list(candidates)
    for size in range(len(names) + 1):
        for groups in combinations(names, size):
            extended = model.with_sensors([s for g in groups for s in candidates[g]])
            fault_rows = extended.fault_equation_index()[:len(original)]
            detectable, not_isolable = isolability_by_overdetermined_part(
                extended.incidence(extended.unknown), fault_rows)
            labels = labels_from_isolability(detectable, not_isolable)
            results.append({'groups': groups,
                            'non_isolable_pairs': int(not_isolable.sum() - len(original)),
                            'labels': dict(zip(original, labels))})
    return results
