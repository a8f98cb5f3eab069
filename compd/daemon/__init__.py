"""The daemon behind `compd run`: the pipeline's owner (App), one pipeline at a time, stop and reload."""
