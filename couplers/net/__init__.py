"""The net folder and its import: net, routes, zones, areas, buildings and georeference."""
