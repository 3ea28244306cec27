// kdrt upload, meshes, info, rm: the stored meshes.

#include <algorithm>
#include <optional>

#include "cli_command.h"
#include "cli_context.h"
#include "cli_output.h"
#include "kdrt/proto/json_api.h"

namespace kdrt::cli {
namespace {

constexpr std::string_view kUploadHelp =
    R"(usage: kdrt upload FILE... [--format obj|ply|off|stl|raw] [--json] [--quiet]

Uploads each mesh file; the server builds its kD-tree and stores it. Prints one line per file:
  ID  TRIANGLES triangles  BUILD_MS ms  FILE
Uploading the same triangles again (in any format) returns the stored mesh without a rebuild.

  --format F   the format of every FILE (default: from each extension: .obj .ply .off .stl,
               .raw/.kdrtmesh for the raw format)
  --json       print one JSON object per file, one per line: "file" and the server's fields
               (id, triangles, vertices, bounds, build_ms, tree, in_memory)
  -q, --quiet  print only each mesh's ID

A file the server cannot parse is reported with its line or byte (exit 1); the other files are
still uploaded.
)";

constexpr OptionSpec kUploadOptions[] = {{"format", true}};

int run_upload(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, SIZE_MAX, "FILE (the mesh files to upload)", code))
        return code;
    std::optional<proto::MeshFormat> format;
    if (auto name = ctx.args.value("format")) {
        format = proto::mesh_format_from_name(*name);
        if (!format)
            return ctx.usage_error("--format: \"" + *name + "\" is not obj, ply, off, stl or raw");
    }
    const bool json = ctx.json();
    Client& client = ctx.connect(ctx.client_options());
    for (const std::string& file : ctx.args.positional) {
        auto mesh = client.upload(file, format);
        if (!mesh) {
            const int failed = ctx.fail(mesh.error(), file);
            if (failed == kExitUnreachable)
                return failed;  // the other files would fail the same way
            code = std::max(code, failed);
            continue;
        }
        ctx.console.out << (json          ? mesh_json_line(*mesh, file)
                            : ctx.quiet() ? mesh->id
                                          : upload_line(*mesh, file))
                        << "\n"
                        << std::flush;
    }
    return code;
}

constexpr std::string_view kMeshesHelp = R"(usage: kdrt meshes [--json] [--quiet]

Lists the stored meshes, sorted by id: ID, TRIANGLES, VERTICES, BUILD_MS, IN_MEMORY.

  --json        one JSON object per mesh, one per line (the server's fields)
  -q, --quiet   print only the IDs, one per line
)";

int run_meshes(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 0, 0, "", code)) return code;
    auto list = ctx.connect(ctx.client_options()).meshes();
    if (!list) return ctx.fail(list.error());
    if (ctx.json()) {
        for (const MeshInfo& m : *list) ctx.console.out << mesh_json_line(m) << "\n";
    } else if (ctx.quiet()) {
        for (const MeshInfo& m : *list) ctx.console.out << m.id << "\n";
    } else if (list->empty()) {
        ctx.console.out << "no meshes stored\n";
    } else {
        ctx.console.out << mesh_table(*list);
    }
    return kExitOk;
}

constexpr std::string_view kInfoHelp = R"(usage: kdrt info ID [--json] [--quiet]

Shows one stored mesh: triangles, vertices, bounds, build time and kD-tree statistics.

  --json        the server's JSON object on one line
  -q, --quiet   print only the full ID (e.g. of a prefix), exit 1 if there is no such mesh
)";

int run_info(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, 1, "ID (a mesh id)", code)) return code;
    ctx.connect(ctx.client_options());
    auto id = ctx.resolve_mesh_id(ctx.args.positional[0]);
    if (!id) return id.error();
    auto mesh = ctx.client->mesh(*id);
    if (!mesh) return ctx.fail(mesh.error());
    ctx.console.out << (ctx.json()    ? mesh_json_line(*mesh) + "\n"
                        : ctx.quiet() ? mesh->id + "\n"
                                      : mesh_details(*mesh));
    return kExitOk;
}

constexpr std::string_view kRmHelp = R"(usage: kdrt rm ID... [--json] [--quiet]

Deletes stored meshes (their files on the server too). Prints "removed ID" per mesh.

  --json        {"removed": ID} per mesh instead
  -q, --quiet   print nothing but errors
)";

int run_rm(Context& ctx) {
    int code = kExitOk;
    if (!positional_count_ok(ctx, 1, SIZE_MAX, "ID (the meshes to delete)", code)) return code;
    ctx.connect(ctx.client_options());
    for (const std::string& arg : ctx.args.positional) {
        auto id = ctx.resolve_mesh_id(arg);
        if (!id) {
            if (id.error() == kExitUnreachable) return id.error();
            code = std::max(code, id.error());
            continue;
        }
        auto removed = ctx.client->remove(*id);
        if (!removed) {
            const int failed = ctx.fail(removed.error());
            if (failed == kExitUnreachable) return failed;
            code = std::max(code, failed);
            continue;
        }
        if (ctx.json()) {
            const proto::JsonField fields[] = {{"removed", std::string_view(*id)}};
            ctx.console.out << proto::encode_flat_object(fields) << "\n" << std::flush;
        } else if (!ctx.quiet()) {
            ctx.console.out << "removed " << *id << "\n" << std::flush;
        }
    }
    return code;
}

}  // namespace

constinit const Command kUploadCommand{
    .name = "upload",
    .synopsis = "upload FILE...",
    .summary = "upload mesh files (OBJ, PLY, OFF, STL, raw); print id, triangles, build ms",
    .help = kUploadHelp,
    .options = kUploadOptions,
    .needs_server = true,
    .run = run_upload,
};

constinit const Command kMeshesCommand{
    .name = "meshes",
    .synopsis = "meshes",
    .summary = "list the stored meshes",
    .help = kMeshesHelp,
    .options = {},
    .needs_server = true,
    .run = run_meshes,
};

constinit const Command kInfoCommand{
    .name = "info",
    .synopsis = "info ID",
    .summary = "show one stored mesh",
    .help = kInfoHelp,
    .options = {},
    .needs_server = true,
    .run = run_info,
};

constinit const Command kRmCommand{
    .name = "rm",
    .synopsis = "rm ID...",
    .summary = "delete stored meshes",
    .help = kRmHelp,
    .options = {},
    .needs_server = true,
    .run = run_rm,
};

}  // namespace kdrt::cli
