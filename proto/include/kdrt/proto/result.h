#pragma once
/// A small in-house `expected`: a value of type T or an error of type E (C++20 has no
/// std::expected). proto returns it from every decoder and parser instead of throwing.
///
///   Result<RayBatch, DecodeError> r = decode_rays(body);
///   if (!r) return reply_error(r.error());
///   use(r->rays);
///
/// Accessing value() of an error Result, or error() of a successful one, is a programming error:
/// it prints a message to stderr and aborts (in every build type), never undefined behaviour.

#include <cstdio>
#include <cstdlib>
#include <optional>
#include <type_traits>
#include <utility>
#include <variant>

namespace kdrt::proto {

/// Wraps an error value so it converts to any Result<T, E> whose E is constructible from it:
/// `return Err{DecodeError{...}};` or `return Err{std::string("...")};`.
template <class E>
struct Err {
    E error;
};
template <class E>
Err(E) -> Err<E>;

/// Same as `Err{e}`, for call sites that prefer a function.
template <class E>
[[nodiscard]] constexpr Err<std::decay_t<E>> make_error(E&& error) {
    return Err<std::decay_t<E>>{std::forward<E>(error)};
}

namespace detail {
[[noreturn]] inline void result_bad_access(const char* what) noexcept {
    std::fputs(what, stderr);
    std::fputc('\n', stderr);
    std::abort();
}
}  // namespace detail

/// Either a T (success) or an E (failure). T and E may be the same type.
template <class T, class E>
class [[nodiscard]] Result {
public:
    using value_type = T;
    using error_type = E;

    /// Success from a value (implicit, so `return value;` works).
    Result(const T& value) : data_(std::in_place_index<0>, value) {}
    Result(T&& value) : data_(std::in_place_index<0>, std::move(value)) {}

    /// Failure from an error wrapper (implicit, so `return Err{...};` works).
    // clang-format off  (clang-format 14 folds requires-clauses into the declarator line)
    template <class G>
    requires std::is_constructible_v<E, G&&> Result(Err<G>&& err)
        : data_(std::in_place_index<1>, std::move(err.error)) {}
    template <class G>
    requires std::is_constructible_v<E, const G&> Result(const Err<G>& err)
        : data_(std::in_place_index<1>, err.error) {}
    // clang-format on

    /// Explicit factories; unambiguous even when T and E are the same type.
    [[nodiscard]] static Result success(T value) {
        return Result(std::in_place_index<0>, std::move(value));
    }
    [[nodiscard]] static Result failure(E error) {
        return Result(std::in_place_index<1>, std::move(error));
    }

    /// True when the Result holds a value.
    [[nodiscard]] bool ok() const noexcept { return data_.index() == 0; }
    explicit operator bool() const noexcept { return ok(); }

    /// The value. Aborts if the Result holds an error.
    [[nodiscard]] T& value() & {
        check_value();
        return std::get<0>(data_);
    }
    [[nodiscard]] const T& value() const& {
        check_value();
        return std::get<0>(data_);
    }
    [[nodiscard]] T&& value() && {
        check_value();
        return std::get<0>(std::move(data_));
    }

    [[nodiscard]] T& operator*() & { return value(); }
    [[nodiscard]] const T& operator*() const& { return value(); }
    [[nodiscard]] T&& operator*() && { return std::move(*this).value(); }
    [[nodiscard]] T* operator->() { return &value(); }
    [[nodiscard]] const T* operator->() const { return &value(); }

    /// The value, or `fallback` if the Result holds an error.
    template <class U>
    [[nodiscard]] T value_or(U&& fallback) const& {
        return ok() ? std::get<0>(data_) : static_cast<T>(std::forward<U>(fallback));
    }

    /// The error. Aborts if the Result holds a value.
    [[nodiscard]] E& error() & {
        check_error();
        return std::get<1>(data_);
    }
    [[nodiscard]] const E& error() const& {
        check_error();
        return std::get<1>(data_);
    }
    [[nodiscard]] E&& error() && {
        check_error();
        return std::get<1>(std::move(data_));
    }

private:
    template <size_t I, class V>
    Result(std::in_place_index_t<I> tag, V&& v) : data_(tag, std::forward<V>(v)) {}

    void check_value() const noexcept {
        if (!ok()) detail::result_bad_access("kdrt::proto::Result: value() called on an error");
    }
    void check_error() const noexcept {
        if (ok()) detail::result_bad_access("kdrt::proto::Result: error() called on a value");
    }

    std::variant<T, E> data_;
};

/// Success without a value, or an E.
template <class E>
class [[nodiscard]] Result<void, E> {
public:
    using value_type = void;
    using error_type = E;

    /// Success.
    Result() = default;

    /// Failure from an error wrapper.
    // clang-format off
    template <class G>
        requires std::is_constructible_v<E, G&&>
    Result(Err<G>&& err) : error_(std::in_place, std::move(err.error)) {}
    template <class G>
        requires std::is_constructible_v<E, const G&>
    Result(const Err<G>& err) : error_(std::in_place, err.error) {}
    // clang-format on

    [[nodiscard]] static Result success() { return Result(); }
    [[nodiscard]] static Result failure(E error) { return Result(Err<E>{std::move(error)}); }

    [[nodiscard]] bool ok() const noexcept { return !error_.has_value(); }
    explicit operator bool() const noexcept { return ok(); }

    /// The error. Aborts if the Result is a success.
    [[nodiscard]] E& error() & {
        check_error();
        return *error_;
    }
    [[nodiscard]] const E& error() const& {
        check_error();
        return *error_;
    }
    [[nodiscard]] E&& error() && {
        check_error();
        return std::move(*error_);
    }

private:
    void check_error() const noexcept {
        if (ok())
            detail::result_bad_access("kdrt::proto::Result<void>: error() called on a success");
    }

    std::optional<E> error_;
};

}  // namespace kdrt::proto
