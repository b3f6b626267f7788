"""Ontologies: offline loading with imports, name resolution, subclass matching, individuals."""

from __future__ import annotations

import logging
import socket
from pathlib import Path

import pytest
from rdflib import BNode, Graph, URIRef
from rdflib.namespace import OWL, RDF, RDFS

from dyknow.errors import DyKnowError, OntologyError
from dyknow.ontology import Ontology
from dyknow.spec import parse_specs
from dyknow.tags import parse_term

REPO = Path(__file__).resolve().parent.parent
DYKNOW_TTL = REPO / "specs" / "dyknow.ttl"
FIXTURES = Path(__file__).resolve().parent / "ontology"
DK = "https://dyknow.dev/ontology#"
SOSA = "http://www.w3.org/ns/sosa/"
SSN = "http://www.w3.org/ns/ssn/"
DUL_IRI = "http://www.ontologydesignpatterns.org/ont/dul/DUL.owl"


@pytest.fixture(scope="module")
def dyknow() -> Ontology:
    return Ontology.load(DYKNOW_TTL)


@pytest.fixture
def ontology_dir(data_dir: Path) -> Path:
    return (data_dir / "ontology").resolve()  # the loader reports resolved paths


# -- the project's example ontology ---------------------------------------------------------------


def test_example_ontology_loads_alone(dyknow: Ontology) -> None:
    assert dyknow.files == (str(DYKNOW_TTL),)
    assert len(dyknow) > 0
    for name in ("Camera", "RobotCamera", "CeilingCamera", "Frame", "Image", "RawImage", "YUVImage", "BGRImage",
                 "HSVImage", "GreyImage", "UndistortedImage", "AnnotatedImage", "WorldObject", "BallObject",
                 "Detection", "BallDetection", "Position", "BallPosition", "BallTrack", "Measure"):  # fmt: skip
        assert DK + name in dyknow.classes, name
    # SOSA is referred to by IRI, not imported: the file loads on its own.
    assert dyknow.resolve("sosa:Sensor") == SOSA + "Sensor"


def test_every_example_class_has_a_label_and_comment() -> None:
    graph = Graph().parse(DYKNOW_TTL, format="turtle")
    for cls in graph.subjects(RDF.type, OWL.Class):
        assert graph.value(cls, RDFS.label) is not None, cls
        assert graph.value(cls, RDFS.comment) is not None, cls


def test_paper_example_subclass_satisfies_superclass(dyknow: Ontology) -> None:
    assert dyknow.matches("BallObject(rel)", "WorldObject(rel)")
    assert not dyknow.matches("WorldObject(rel)", "BallObject(rel)")
    assert dyknow.matches(parse_term("BallObject(rel)"), parse_term("WorldObject(rel)"))


def test_subclass_is_reflexive_and_transitive(dyknow: Ontology) -> None:
    assert dyknow.matches("BallTrack(field)", "BallPosition(field)")
    assert dyknow.matches("BallTrack(field)", "Position(field)")
    assert dyknow.matches("BallPosition(field)", "BallPosition(field)")
    assert not dyknow.matches("Position(field)", "BallTrack(field)")
    assert not dyknow.matches("BallDetection(top)", "BallPosition(top)")
    assert dyknow.is_subclass(DK + "YUVImage", DK + "Image")
    assert dyknow.is_subclass(DK + "RobotCamera", SOSA + "Sensor")
    assert not dyknow.is_subclass(DK + "Image", DK + "YUVImage")
    assert not dyknow.is_subclass(DK + "YUVImage", DK + "RawImage")  # raw frames are BGR
    assert dyknow.descendants(DK + "Position") == {DK + "Position", DK + "BallPosition", DK + "BallTrack"}
    assert dyknow.descendants(DK + "field") == {DK + "field"}  # an individual is no class


@pytest.mark.parametrize("arg", ["rel", "dk:rel", f"<{DK}rel>", " rel "])
def test_args_compare_by_local_name(dyknow: Ontology, arg: str) -> None:
    assert dyknow.matches(f"BallObject({arg})", "WorldObject(rel)")
    assert dyknow.matches("BallObject(rel)", f"WorldObject({arg})")
    assert not dyknow.matches(f"BallObject({arg})", "WorldObject(field)")


def test_arg_count_must_agree(dyknow: Ontology) -> None:
    assert not dyknow.matches("BallPosition(field)", "BallPosition")
    assert not dyknow.matches("BallPosition", "BallPosition(field)")
    assert not dyknow.matches("Undistorted(top, rel)", "Undistorted(top)")


def test_unknown_functors_match_only_themselves(dyknow: Ontology) -> None:
    assert dyknow.resolve("Odometry") is None
    assert dyknow.matches("Odometry(rel)", "Odometry(rel)")
    assert dyknow.matches("ex:Odometry", "Odometry")  # unresolved both: equal local names
    assert not dyknow.matches("Odometry", "Position")
    assert not dyknow.matches("Position", "Odometry")
    # dk:Odometry names no class: unresolved, so it cannot match the class dk:Position.
    assert dyknow.resolve("dk:Odometry") is None
    assert not dyknow.matches("dk:Odometry", "Position")


def test_empty_ontology_matches_names_only() -> None:
    empty = Ontology.empty()
    assert len(empty) == 0 and empty.files == () and empty.classes == frozenset()
    assert empty.resolve("BallPosition") is None
    assert empty.matches("BallPosition(field)", "BallPosition(field)")
    assert empty.matches("BallPosition(dk:field)", "ex:BallPosition(field)")
    assert not empty.matches("BallTrack(field)", "BallPosition(field)")
    with pytest.raises(OntologyError, match="no ontology with classes is loaded; expected --ontology FILE"):
        empty.individuals("dk:Camera")


# -- name resolution ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "iri"),
    [
        ("BallPosition", DK + "BallPosition"),  # local name among classes
        (" BallPosition ", DK + "BallPosition"),
        ("dk:BallPosition", DK + "BallPosition"),  # prefix declared in the file
        (f"<{DK}BallPosition>", DK + "BallPosition"),  # full IRI
        (f"{DK}BallPosition", DK + "BallPosition"),  # bare IRI
        ("ex:BallPosition", DK + "BallPosition"),  # undeclared prefix: by local name
        ("dk:field", DK + "field"),  # an individual, by prefixed name
        ("field", None),  # local names find classes only
        ("dk:NoSuchThing", None),
        (f"<{DK}NoSuchThing>", None),
        ("NoSuchThing", None),
    ],
)
def test_resolve(dyknow: Ontology, name: str, iri: str | None) -> None:
    assert dyknow.resolve(name) == iri


def test_ambiguous_local_name_lists_the_candidates() -> None:
    onto = Ontology.load(FIXTURES / "ambiguous.ttl")
    for call in (lambda: onto.resolve("Camera"), lambda: onto.matches("Camera", "Camera"),
                 lambda: onto.individuals("Camera")):  # fmt: skip
        with pytest.raises(OntologyError) as caught:
            call()
        message = str(caught.value)
        assert "'Camera' is ambiguous" in message
        assert "<http://acme.example/vision#Camera> (acme:Camera)" in message
        assert "<http://robo.example/ns/Camera> (robo:Camera)" in message
        assert "write a prefixed name or a full IRI in angle brackets" in message
    assert onto.resolve("acme:Camera") == "http://acme.example/vision#Camera"
    assert onto.resolve("<http://robo.example/ns/Camera>") == "http://robo.example/ns/Camera"
    assert onto.resolve("Lens") == "http://acme.example/vision#Lens"
    assert onto.matches("robo:Camera(x)", "robo:Sensor(x)")
    assert not onto.matches("acme:Camera(x)", "robo:Sensor(x)")
    assert onto.individuals("robo:Camera") == ["head"]


def test_conflicting_prefixes_first_file_wins() -> None:
    first, second = FIXTURES / "prefix-first.ttl", FIXTURES / "prefix-second.ttl"
    onto = Ontology.load([first, second])
    assert onto.resolve("ex:Widget") == "http://first.example/ns#Widget"
    assert onto.resolve("ex:Gadget") is None  # ex: is the first file's namespace, which has no Gadget
    assert onto.resolve("Gadget") == "http://second.example/ns#Gadget"
    assert Ontology.load([second, first]).resolve("ex:Widget") == "http://second.example/ns#Widget"
    with pytest.raises(OntologyError, match="'Widget' is ambiguous"):
        onto.resolve("Widget")


# -- individuals ----------------------------------------------------------------------------------


def test_individuals_of_the_example_ontology(dyknow: Ontology) -> None:
    assert dyknow.individuals("dk:Camera") == ["bottom", "ceiling", "top"]
    assert dyknow.individuals("Camera") == ["bottom", "ceiling", "top"]
    assert dyknow.individuals(f"<{DK}RobotCamera>") == ["bottom", "top"]
    assert dyknow.individuals("dk:CeilingCamera") == ["ceiling"]
    assert dyknow.individuals("dk:Frame") == ["field", "rel"]
    assert dyknow.individuals("dk:Measure") == ["battery"]
    assert dyknow.individuals("dk:Image") == []


def test_individuals_of_an_unknown_class(dyknow: Ontology) -> None:
    with pytest.raises(OntologyError, match=r"unknown ontology class 'dk:Camra'.*did you mean 'dk:Camera'"):
        dyknow.individuals("dk:Camra")
    with pytest.raises(OntologyError, match=r"unknown ontology class 'Framee'.*did you mean 'Frame'"):
        dyknow.individuals("Framee")
    with pytest.raises(OntologyError, match=r"'dk:bottom' is <https://dyknow.dev/ontology#bottom>, which is no class"):
        dyknow.individuals("dk:bottom")


def test_individual_names_prefer_labels() -> None:
    onto = Ontology.load(FIXTURES / "labels.ttl")
    # unlabelled -> local name; "zeta"/"alpha" -> smallest; @fr/@en-GB -> English; @de/@en/plain ->
    # plain; @fr only -> that label; a subclass member; "twice" typed twice and shared: once.
    assert onto.individuals("ex:Thing") == ["Hello", "Salut", "alpha", "deep", "plainly", "twice", "unlabelled"]
    assert onto.individuals("SubThing") == ["deep", "twice"]
    assert onto.individuals("Other") == ["elsewhere"]


def test_template_args_expand_to_individuals(dyknow: Ontology) -> None:
    xml = """<transformation>
      <label>undistort(${Cam})</label>
      <source>transformations.vision:Undistort</source>
      <args><arg label="Cam" class="dk:Camera"/></args>
      <ports><port type="out">undist</port></ports>
      <tags><tag port="undist">UndistortedImage(${Cam})</tag></tags>
    </transformation>"""
    specs = parse_specs(xml, individuals=dyknow.individuals)
    assert [s.label for s in specs] == ["undistort(bottom)", "undistort(ceiling)", "undistort(top)"]
    assert dyknow.matches(specs[0].tags_for("undist")[0], "Image(dk:bottom)")


# -- loading real files and their imports ---------------------------------------------------------


def test_ssn_imports_sosa_from_the_same_folder(ontology_dir: Path) -> None:
    onto = Ontology.load(ontology_dir / "ssn.ttl")
    assert onto.files == (str(ontology_dir / "ssn.ttl"), str(ontology_dir / "sosa.ttl"))
    assert onto.is_subclass(SOSA + "Sensor", SSN + "System")
    assert onto.matches("sosa:Sensor", "ssn:System")
    assert not Ontology.load(ontology_dir / "sosa.ttl").is_subclass(SOSA + "Sensor", SSN + "System")


def test_example_ontology_joins_sosa_and_ssn(ontology_dir: Path) -> None:
    onto = Ontology.load([DYKNOW_TTL, ontology_dir / "sosa.ttl", ontology_dir / "ssn.ttl"])
    assert len(onto.files) == 3  # ssn's import of sosa is the sosa.ttl already given
    assert onto.is_subclass(DK + "Camera", SSN + "System")
    assert onto.is_subclass(DK + "RobotCamera", SSN + "System")
    assert onto.matches("RobotCamera(top)", "ssn:System(top)")
    assert onto.individuals("sosa:Sensor") == ["bottom", "ceiling", "top"]
    assert not Ontology.load(DYKNOW_TTL).is_subclass(DK + "Camera", SSN + "System")


def test_loading_never_uses_the_network(ontology_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"network access while loading an ontology: {args}")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    onto = Ontology.load(ontology_dir / "ssn-system.ttl")
    assert [Path(f).name for f in onto.files] == ["ssn-system.ttl", "ssn.ttl", "sosa.ttl"]
    assert onto.is_subclass(SOSA + "Sensor", SSN + "System")


def test_missing_import_is_an_error_naming_it(ontology_dir: Path) -> None:
    with pytest.raises(OntologyError) as caught:
        Ontology.load(ontology_dir / "ssn-dul.ttl")
    message = str(caught.value)
    assert f"{ontology_dir / 'ssn-dul.ttl'}: owl:imports <{DUL_IRI}> is not available offline" in message
    assert f"looked in {ontology_dir} for DUL.owl, DUL.{{ttl,n3,rdf,owl,xml,nt}}" in message
    assert "pass imports={IRI: PATH} (CLI: --ontology PATH)" in message
    assert "missing_imports='warn'" in message
    assert "<http://www.w3.org/ns/sosa/sampling> is not available offline" in message  # every missing one


def test_missing_import_can_be_a_warning(ontology_dir: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="dyknow.ontology"):
        onto = Ontology.load([ontology_dir / "ssn-dul.ttl", ontology_dir / "ssn.ttl"], missing_imports="warn")
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(DUL_IRI in m and "going on without it" in m for m in warned), warned
    assert [Path(f).name for f in onto.files] == ["ssn-dul.ttl", "ssn.ttl", "sosa.ttl"]
    # The DUL classes are known only as the superclasses ssn-dul.ttl names; nothing above them.
    assert onto.matches("Platform(x)", "dul:Object(x)")
    assert not onto.matches("Platform(x)", "dul:PhysicalObject(x)")
    assert onto.matches("sosa:Sensor", "ssn:System")


def test_missing_imports_option_is_checked() -> None:
    with pytest.raises(ValueError, match="missing_imports='ignore'; expected 'error' or 'warn'"):
        Ontology.load(DYKNOW_TTL, missing_imports="ignore")


def test_imports_by_name_by_declaration_and_in_cycles() -> None:
    folder = FIXTURES / "imports"
    onto = Ontology.load(folder / "app.ttl")
    # base.ttl by its file name, extra-module.ttl by its owl:Ontology declaration (with a '#'
    # of difference); base.ttl imports app.ttl back, which is loaded once; the broken neighbour
    # file is skipped while looking.
    assert [Path(f).name for f in onto.files] == ["app.ttl", "base.ttl", "extra-module.ttl"]
    assert onto.matches("app:Special", "base:Root")
    assert onto.matches("Addon", "extra:Extra")


def test_imports_from_the_mapping_or_search_dirs() -> None:
    needs, copy = FIXTURES / "imports" / "needs-far.ttl", FIXTURES / "far" / "remote-copy.ttl"
    with pytest.raises(OntologyError, match="<http://example.org/onto/far-away> is not available offline"):
        Ontology.load(needs)
    for onto in (
        Ontology.load(needs, imports={"http://example.org/onto/far-away": copy}),
        Ontology.load(needs, imports={"<http://example.org/onto/far-away/>": str(copy)}),
        Ontology.load(needs, search_dirs=[FIXTURES / "far"]),
    ):
        assert onto.files == (str(needs), str(copy))
        assert onto.matches("Close", "far:Anywhere")


def test_bad_import_mapping_and_search_dirs() -> None:
    needs = FIXTURES / "imports" / "needs-far.ttl"
    with pytest.raises(OntologyError, match=r"local copy of <http://example.org/onto/far-away> .*not found"):
        Ontology.load(needs, imports={"http://example.org/onto/far-away": FIXTURES / "nowhere.ttl"})
    with pytest.raises(OntologyError, match=r"search_dirs: '.*nowhere' is not a folder"):
        Ontology.load(needs, search_dirs=[FIXTURES / "nowhere"])


def test_missing_file_and_folder() -> None:
    with pytest.raises(OntologyError, match=r"ontology file '.*no-such\.ttl' not found; expected an existing Turtle"):
        Ontology.load(FIXTURES / "no-such.ttl")
    with pytest.raises(OntologyError, match=r"ontology file '.*ontology' is a folder; expected a file"):
        Ontology.load(FIXTURES)


def test_malformed_file_is_located_and_nothing_is_loaded(data_dir: Path) -> None:
    broken = (data_dir / "ontology" / "examples" / "tree-height-sosa.ttl").resolve()
    with pytest.raises(OntologyError) as caught:
        Ontology.load([DYKNOW_TTL, broken])
    message = str(caught.value)
    assert message.startswith(f"{broken}:30: ")
    assert 'Prefix "ssn:" not bound' in message and "expected valid Turtle" in message
    assert isinstance(caught.value, DyKnowError)
    # No state survives the failed load: the good file alone loads the same as before.
    assert len(Ontology.load(DYKNOW_TTL)) == len(Graph().parse(DYKNOW_TTL, format="turtle"))


def test_malformed_import_names_its_importer() -> None:
    wants, broken = FIXTURES / "imports" / "wants-broken.ttl", FIXTURES / "imports" / "broken-neighbour.ttl"
    with pytest.raises(OntologyError) as caught:
        Ontology.load(wants)
    message = str(caught.value)
    assert message.startswith(f"{broken}:3: ") and "expected valid Turtle" in message
    assert message.endswith(f"(imported as <http://example.org/onto/broken-neighbour> by {wants})")


def test_real_example_files_load(data_dir: Path) -> None:
    examples = data_dir / "ontology" / "examples"
    onto = Ontology.load(examples / "dht22-sosa.ttl", search_dirs=[data_dir / "ontology"])
    assert onto.resolve("sosa:Sensor") == SOSA + "Sensor"
    core = Ontology.load(examples / "sosa-core_examples.ttl", search_dirs=[data_dir / "ontology"])
    assert [Path(f).name for f in core.files] == ["sosa-core_examples.ttl", "sosa.ttl"]


@pytest.mark.parametrize(
    ("name", "iri"),
    [
        ("vehicles.rdf", "http://example.org/vehicles#Car"),
        ("vehicles.nt", "http://example.org/vehicles#Truck"),
        ("turtle-without-extension.txt", "http://example.org/vehicles#Bike"),
        ("rdfxml-without-extension.txt", "http://example.org/vehicles#Boat"),
    ],
)
def test_other_formats(name: str, iri: str) -> None:
    onto = Ontology.load(FIXTURES / "formats" / name)
    assert onto.is_subclass(iri, "http://example.org/vehicles#Vehicle")
    assert onto.matches(iri.rpartition("#")[2], "Vehicle")


def test_rdfxml_prefixes_and_individuals() -> None:
    onto = Ontology.load(FIXTURES / "formats" / "vehicles.rdf")
    assert onto.resolve("veh:Car") == "http://example.org/vehicles#Car"
    assert onto.individuals("veh:Vehicle") == ["Herbie"]


def test_syntax_errors_in_other_formats() -> None:
    broken = FIXTURES / "formats" / "broken.rdf"
    with pytest.raises(OntologyError, match=rf"^{broken}:6: mismatched tag; expected valid RDF/XML$"):
        Ontology.load(broken)
    neither = FIXTURES / "formats" / "neither.txt"
    with pytest.raises(OntologyError) as caught:
        Ontology.load(neither)
    message = str(caught.value)
    assert message.startswith(f"{neither}: neither Turtle nor RDF/XML")
    assert f"as Turtle: {neither}:1:" in message and f"as RDF/XML: {neither}:1:" in message


# -- the precomputed closure against a reference --------------------------------------------------


def _reference_closure(graph: Graph) -> set[tuple[object, object]]:
    """Reflexive-transitive rdfs:subClassOf by naive fixpoint (rdfs5 and rdfs10), blank nodes kept."""
    edges = {(s, o) for s, o in graph.subject_objects(RDFS.subClassOf) if isinstance(o, URIRef | BNode)}
    nodes = {n for edge in edges for n in edge}
    closure = edges | {(n, n) for n in nodes}
    while True:
        by_start: dict[object, set[object]] = {}
        for a, b in closure:
            by_start.setdefault(a, set()).add(b)
        new = {(a, c) for a, b in closure for c in by_start.get(b, ())} - closure
        if not new:
            return closure
        closure |= new


def test_closure_matches_a_reference_on_ssn(ontology_dir: Path) -> None:
    files = [ontology_dir / "ssn-system.ttl", ontology_dir / "ssn.ttl", ontology_dir / "sosa.ttl"]
    onto = Ontology.load(files)
    graph = Graph()
    for file in files:
        graph.parse(file, format="turtle")
    closure = _reference_closure(graph)
    classes = {str(n) for edge in closure for n in edge if isinstance(n, URIRef)}
    classes |= {str(s) for kind in (OWL.Class, RDFS.Class) for s in graph.subjects(RDF.type, kind)
                if isinstance(s, URIRef)}  # fmt: skip
    assert onto.classes == classes
    assert len(classes) > 40
    pairs = {(str(a), str(b)) for a, b in closure if isinstance(a, URIRef) and isinstance(b, URIRef)}
    assert len(pairs) > len(classes)  # there is a hierarchy to get right
    for sub in sorted(classes):
        for sup in sorted(classes):
            assert onto.is_subclass(sub, sup) == (sub == sup or (sub, sup) in pairs), (sub, sup)
        assert onto.descendants(sub) == {sub} | {a for a, b in pairs if b == sub}
