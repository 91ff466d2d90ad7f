"""A custom import-linter contract type: no import cycle among the modules of each wing.

Registered in ``pyproject.toml`` (``[tool.importlinter] contract_types``) and run by ``lint-imports`` from the
repository root (docs/architecture.md, "The import rules", rule 5): import-linter's own ``acyclic_siblings`` squashes
each package's children, so it misses cycles through a package's ``__init__`` or between two packages of a wing and
flags package-level cycles that no module closes. Here every module belongs to one wing (:func:`wing_of`), and the
imports among one wing's modules — function-local ones and those under ``TYPE_CHECKING`` included, as grimp records
them — must form no cycle. A wing is one string, ``"<name>: <package>, <package>, ..."``, in the contract's ``wings``
list (``type = "acyclic_wings"``). A broken contract lists each cycle once, as a chain of imports with line numbers.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from itertools import pairwise

import grimp
from importlinter.application import output
from importlinter.domain import fields
from importlinter.domain.contract import Contract, ContractCheck


def parse_wings(specs: Iterable[str]) -> dict[str, list[str]]:
    """``["name: pkg, pkg", ...]`` → ``{name: [pkg, ...]}``; ValueError for a malformed or repeated entry."""
    wings: dict[str, list[str]] = {}
    owner: dict[str, str] = {}
    for spec in specs:
        name, sep, packages = spec.partition(":")
        members = [p.strip() for p in packages.replace(",", " ").split()]
        if not sep or not name.strip() or not members:
            raise ValueError(f"wing {spec!r}: expected '<name>: <package>, <package>, ...'")
        for package in members:
            if package in owner:
                raise ValueError(f"package {package} is in two wings: {owner[package]} and {name.strip()}")
            owner[package] = name.strip()
        wings[name.strip()] = members
    return wings


def wing_of(module: str, owner: Mapping[str, str]) -> str | None:
    """The wing of ``module``: the one listing the longest package that is ``module`` or contains it."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        wing = owner.get(".".join(parts[:n]))
        if wing is not None:
            return wing
    return None


def strongly_connected(nodes: Iterable[str], edges: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(nodes):
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return sorted(found)


def one_cycle(component: list[str], edges: Mapping[str, set[str]]) -> list[str]:
    """A shortest import chain from the component's first module back to itself, inside the component."""
    start, members = component[0], set(component)
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(edges.get(node, set()) & members):
                if child == start:
                    chain = [node]
                    while chain[-1] != start:
                        chain.append(previous[chain[-1]])
                    return [*reversed(chain), start]
                if child not in previous:
                    previous[child] = node
                    following.append(child)
        frontier = following
    raise AssertionError(f"no cycle through {start} in {component}")  # a component of > 1 node has one


class AcyclicWingsContract(Contract):
    """No import cycle among the modules of each wing (see the module docstring)."""

    type_name = "acyclic_wings"

    wings = fields.ListField(subfield=fields.StringField())

    def check(self, graph: grimp.ImportGraph, verbose: bool) -> ContractCheck:
        wings = parse_wings(self.wings)  # type: ignore[arg-type]
        owner = {package: wing for wing, packages in wings.items() for package in packages}
        missing = sorted(package for package in owner if package not in graph.modules)
        if missing:
            raise ValueError(f"acyclic_wings: no such package: {', '.join(missing)}")
        members: dict[str, set[str]] = {wing: set() for wing in wings}
        for module in graph.modules:
            wing = wing_of(module, owner)
            if wing is not None:
                members[wing].add(module)
        cycles = []
        for wing in wings:
            modules = members[wing]
            edges = {m: graph.find_modules_directly_imported_by(m) & modules for m in modules}
            for component in strongly_connected(modules, edges):
                steps = [(importer, imported, sorted({d["line_number"] for d in graph.get_import_details(
                    importer=importer, imported=imported)}))
                         for importer, imported in pairwise(one_cycle(component, edges))]
                cycles.append({"wing": wing, "modules": component, "chain": steps})
        return ContractCheck(kept=not cycles, warnings=[], metadata={"cycles": cycles})

    def render_broken_contract(self, check: ContractCheck) -> None:
        for cycle in check.metadata["cycles"]:
            output.print_error(f"Import cycle in the {cycle['wing']} wing among {', '.join(cycle['modules'])}:")
            output.new_line()
            for importer, imported, lines in cycle["chain"]:
                where = ", ".join(f"l.{n}" for n in lines)
                output.print_error(f"- {importer} -> {imported} ({where})", bold=False)
            output.new_line()
