"""The extra bytes of a LAS point format as all of a file's extra-bytes VLRs describe them: laspy reads only the
first VLR, drops no-data values and calls the bytes after its fields one `ExtraBytes` run."""
from __future__ import annotations

import laspy
from laspy.vlrs.known import ExtraBytesVlr


def described_point_format(header: laspy.LasHeader) -> laspy.PointFormat:
    """The header's point format with its extra bytes as all of its extra-bytes VLRs describe them (name, type,
    scale, offset, no-data value, description): laspy reads only the first VLR, drops no-data values and calls the
    bytes after the first VLR's fields one `ExtraBytes` run (las_with_several_extra_byte_bloc.laz holds two VLRs).
    Bytes no VLR describes stay one `ExtraBytes` run; laspy's format is kept where the VLRs describe more bytes
    than a record holds or name two fields alike."""
    fields = [params for vlr in header.vlrs if isinstance(vlr, ExtraBytesVlr) for params in extra_bytes_params(vlr)]
    undescribed = header.point_format.num_extra_bytes - sum(params.type.itemsize for params in fields)
    if not fields or undescribed < 0 or len({params.name for params in fields}) < len(fields):
        return header.point_format
    described = laspy.PointFormat(header.point_format.id)
    for params in fields:
        described.add_extra_dimension(params)
    if undescribed:
        described.add_extra_dimension(laspy.ExtraBytesParams("ExtraBytes", f"{undescribed}u1",
                                                             "Un-registered ExtraBytes"))
    return described


def extra_bytes_params(vlr: ExtraBytesVlr) -> list[laspy.ExtraBytesParams]:
    """The fields one extra-bytes VLR describes, as laspy reads them, with the no-data values laspy leaves out
    (none for undocumented bytes, data type 0, whose options field is their count, not flags)."""
    fields = vlr.type_of_extra_dims()
    for params, field in zip(fields, vlr.extra_bytes_structs):
        params.no_data = field.no_data if field.data_type else None
    return fields
