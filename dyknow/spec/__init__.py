"""Transformation specifications: the XML format, its hardened loader and the template expander.

A transformation is a blueprint for a unit (the DyKnow paper's *nodelet*): the Python class to
instantiate, its parameters, its ports and the semantic tags that describe what the ports carry::

    <transformations>                          <!-- or a single <transformation> as the root -->
      <transformation type="unit">             <!-- "unit" (default) or "nodelet" -->
        <label>undistort(${Cam})</label>
        <source>transformations.vision:Undistort</source>
        <description>free text</description>
        <args>
          <arg label="Cam">{cam1; cam2; cam3}</arg>    <!-- an explicit set of values -->
          <arg label="Robot" class="ex:Robot"/>        <!-- the individuals of an ontology class -->
        </args>
        <params>
          <param name="config-path" type="string">/path/${Cam}/</param>  <!-- string|int|float|bool -->
        </params>
        <ports>
          <port type="out" deadline-ms="500">undist</port>
          <port type="in" queue="1" policy="keep-last">rawcamera</port>
        </ports>
        <tags>
          <tag port="undist">Undistorted(${Cam})</tag>
        </tags>
        <priority>1</priority>                 <!-- lower is preferred; DEFAULT_PRIORITY when absent -->
        <constraints>
          <constraint measure="battery" op="&gt;=" value="0.25"/>
        </constraints>
        <requirements>                         <!-- temporal formulas over its outputs (dyknow.reasoning) -->
          <requirement>always[0, 1s] Undistorted(${Cam}).ok</requirement>
        </requirements>
      </transformation>
    </transformations>

The children of ``<transformation>`` come in any order, each at most once; ``label``, ``source``
and ``ports`` are required. ``specs/transformation.xsd`` describes the same format for editors.

A ``<node>`` beside them names a ROS 2 node that dyknow does not spawn, a *managed node*
(:mod:`dyknow.ros2.managed`): it reads as the transformation whose unit drives the node (its
``<source>`` is :data:`~dyknow.spec.model.MANAGED_NODE_SOURCE`, its one output port ``out`` its
topic), so the planner plans with it like a unit::

    <node name="/camera_top" middleware="dds" lifecycle="true" timeout-s="5">  <!-- zenoh (default) or dds -->
      <label>camera-top</label>
      <params><param name="exposure" type="float">0.5</param></params>   <!-- its ROS 2 parameters -->
      <topic type="sensor_msgs/msg/Image" deadline-ms="500">/camera_top/image_raw</topic>
      <tags><tag>RawImage(top)</tag></tags>                             <!-- a tag of its topic -->
      <priority>1</priority>
    </node>

It takes ``label``, ``description``, ``args``, ``params``, ``tags``, ``priority``,
``constraints`` and ``requirements`` as a transformation does, and ``topic`` instead of
``source`` and ``ports``.

A ``<transformation>`` with ``<args>`` is a *template*: ``${Name}`` is replaced by each value of
the arg ``Name`` in the label, source, description, param values, port names, tag texts, tag
``port`` attributes, constraint values and requirements, and ``$$`` stands for a literal ``$``. Several args
expand as their cartesian product, in document order.

Loading happens in two steps. :func:`parse_templates` checks the structure (elements, attributes,
required parts, template variables) and returns :class:`Template` objects; :meth:`Template.expand`
substitutes the args and checks what depends on the substituted text (param values against their
type, port names, tag ports, constraint values, distinct labels), giving
:class:`TransformationSpec` objects. :func:`parse_specs` and :func:`load_specs` do both and report
every problem of every file in one :class:`~dyknow.errors.SpecError`.

The XML is parsed with :mod:`xml.parsers.expat` directly and any DTD is refused before it is read,
so external entities and entity-expansion bombs cannot work.
"""

from __future__ import annotations

from dyknow.spec.model import (
    CONSTRAINT_OPS,
    DEFAULT_MAX_EXPANSIONS,
    DEFAULT_PRIORITY,
    NODE_MIDDLEWARES,
    PARAM_TYPES,
    PATH_MODES,
    PORT_DIRECTIONS,
    QUEUE_POLICIES,
    TRANSFORMATION_TYPES,
    Arg,
    Constraint,
    Individuals,
    Param,
    PathsLike,
    Port,
    Tag,
    TransformationSpec,
)
from dyknow.spec.reader import ELEMENTS, load_specs, parse_specs, parse_templates, spec_files
from dyknow.spec.template import Template

__all__ = [
    "CONSTRAINT_OPS",
    "DEFAULT_MAX_EXPANSIONS",
    "DEFAULT_PRIORITY",
    "ELEMENTS",
    "NODE_MIDDLEWARES",
    "PARAM_TYPES",
    "PATH_MODES",
    "PORT_DIRECTIONS",
    "QUEUE_POLICIES",
    "TRANSFORMATION_TYPES",
    "Arg",
    "Constraint",
    "Individuals",
    "Param",
    "PathsLike",
    "Port",
    "Tag",
    "Template",
    "TransformationSpec",
    "load_specs",
    "parse_specs",
    "parse_templates",
    "spec_files",
]
