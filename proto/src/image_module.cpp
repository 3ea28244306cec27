// kdrt::proto: finding and loading the image module (kdrt/proto/image_module.h).

#include "kdrt/proto/image_module.h"

#include <dlfcn.h>

#include <cstring>
#include <filesystem>
#include <mutex>
#include <system_error>

namespace kdrt::proto {
namespace {

namespace fs = std::filesystem;

/// The directory of the running executable, or empty if /proc/self/exe cannot be read.
fs::path executable_dir() {
    std::error_code ec;
    const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
    return ec ? fs::path() : exe.parent_path();
}

std::string join(const std::vector<std::string>& paths) {
    std::string out;
    for (const std::string& p : paths) out += (out.empty() ? "" : ", ") + p;
    return out;
}

Result<const ImageModuleTable*, std::string> load() {
    const std::vector<std::string> candidates = image_module_candidates();
    for (const std::string& path : candidates) {
        std::error_code ec;
        if (!fs::exists(path, ec)) continue;
        // RTLD_LOCAL: the module's copies of kdrt_proto's symbols stay its own.
        void* handle = ::dlopen(path.c_str(), RTLD_NOW | RTLD_LOCAL);
        if (!handle) {
            const char* why = ::dlerror();
            return Err{"cannot load the image module " + path + ": " +
                       (why ? why : "unknown dlopen error") +
                       ". It needs OpenImageIO: install the Debian package " + KDRT_OIIO_PACKAGE +
                       " (apt-get install " + KDRT_OIIO_PACKAGE + ")"};
        }
        using Entry = const ImageModuleTable* (*)();
        auto entry = reinterpret_cast<Entry>(::dlsym(handle, kImageModuleEntry));
        const ImageModuleTable* table = entry ? entry() : nullptr;
        if (!table)
            return Err{"the image module " + path + " has no " + kImageModuleEntry +
                       " (not a kdrt image module)"};
        if (table->abi != kImageModuleAbi || !table->version ||
            std::strcmp(table->version, KDRT_VERSION) != 0)
            return Err{"the image module " + path + " is from kdrt " +
                       (table->version ? table->version : "?") + " but this kdrt is " +
                       KDRT_VERSION + ": install both from one build or package"};
        return table;  // the handle stays open for the life of the process
    }
    return Err{"encoding PNG, JPEG or EXR needs kdrt's image module " +
               std::string(kImageModuleFile) + ", which is not installed (looked for " +
               join(candidates) + "). Install kdrt's package (it ships the module and depends on " +
               KDRT_OIIO_PACKAGE + "), or build the target kdrt_image_module"};
}

}  // namespace

std::vector<std::string> image_module_candidates() {
    const fs::path dir = executable_dir();
    if (dir.empty()) return {};
    return {(dir / kImageModuleFile).string(),
            (dir / KDRT_IMAGE_MODULE_RELDIR / kImageModuleFile).lexically_normal().string()};
}

Result<const ImageModuleTable*, std::string> image_module() {
    static std::once_flag once;
    static Result<const ImageModuleTable*, std::string> result{nullptr};
    std::call_once(once, [] { result = load(); });
    return result;
}

}  // namespace kdrt::proto
