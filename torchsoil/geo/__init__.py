"""The soil where people look: a run's maps tied to the Earth (georef: RTK GNSS, an anchor or a
local frame) and written for GIS (geotiff, vectors) and ROS viewers (gridmap). docs/export.md."""
